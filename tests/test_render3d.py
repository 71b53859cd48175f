"""The 3D preview (mls_mpm/render3d.py): camera, the surface and volume ray marchers, particle spheres and the
target's silhouette, checked on pixel values of small frames of a ball built from numpy arrays."""
import numpy as np
import pytest

from mls_mpm.field3d import MassField, mass_field
from mls_mpm.render3d import Preview3D, camera, project

N_GRID = 16
DX = 1.0 / N_GRID
DENSITY = 1.0
SIZE = 96
CENTER = np.array([0.5, 0.5, 0.5])
RADIUS = 0.25


def ball(center=CENTER, radius=RADIUS, k=2):
    """Particles filling a ball, k^3 per cell on a lattice, of the rest-density mass."""
    s = (np.arange(N_GRID * k) + 0.5) * DX / k
    x = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    return x[np.linalg.norm(x - center, axis=1) < radius], DENSITY * DX ** 3 / k ** 3


def pixel_radius(r):
    return r * SIZE / (2 * camera()[3])


def distances(center):
    """Distance in pixels of every pixel centre from the projection of a domain point."""
    col, row, _ = project(np.asarray(center)[None], SIZE)
    rr, cc = np.mgrid[:SIZE, :SIZE] + 0.5
    return np.hypot(cc - col[0], rr - row[0])


def test_the_camera_shows_the_whole_domain_centred():
    d, right, up, half = camera()
    assert np.allclose([d @ right, d @ up, right @ up], 0) and np.allclose(np.linalg.norm([d, right, up], axis=1), 1)
    assert d @ np.array([1.0, 0.8, 1.4]) > 0 and up[1] > 0  # looking from (1, 0.8, 1.4), y up
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3)
    col, row, depth = project(corners, SIZE)
    assert col.min() >= -1e-9 and row.min() >= -1e-9 and max(col.max(), row.max()) <= SIZE + 1e-9
    assert min(col.min(), row.min()) < 1e-9  # the cube's projection just fits
    assert np.allclose(project(CENTER[None], SIZE)[:2], SIZE / 2)
    assert np.argmin(depth) == 7  # the corner (1, 1, 1) is the nearest


@pytest.mark.parametrize("mode", ["surface", "volume"])
def test_a_ball_is_a_disc_of_its_radius_red_inside(mode):
    x, m_p = ball()
    img = Preview3D(N_GRID, SIZE, mode).render(mass_field(x, m_p, N_GRID, DENSITY)).astype(int)
    dist = distances(CENTER)
    drawn = np.any(img != 255, axis=2)
    assert not drawn[dist > pixel_radius(RADIUS + 2.5 * DX)].any()  # the smoothing reaches 2 cells
    inner = dist < pixel_radius(RADIUS - 2 * DX)
    assert drawn[inner].all()
    r, g, b = img[inner].T
    assert (r > g + 40).all() and (r > b + 40).all()  # red: at rest density (t = 1) inside
    if mode == "surface":  # the surface's outline is the level-1/2 sphere: the ball's radius within half a cell
        area = np.count_nonzero(drawn)
        assert np.sqrt(area / np.pi) == pytest.approx(pixel_radius(RADIUS), abs=pixel_radius(0.5 * DX))
        lit = img[inner].sum(axis=1)
        assert lit.max() - lit.min() > 60  # Lambert shading varies over the ball
    else:  # a thin edge shows through: brighter (less opaque) than the centre
        rim = (dist > pixel_radius(RADIUS)) & (dist < pixel_radius(RADIUS + DX))
        assert img[rim].sum(axis=1).mean() > img[dist < 3].sum(axis=1).mean() + 50


def test_the_colors_of_a_colour_scene_are_shown():
    x, m_p = ball()
    right_axis = camera()[1]
    side = (x - CENTER) @ right_axis
    colors = np.where(side[:, None] < 0, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])  # the view's left half red, right blue
    img = Preview3D(N_GRID, SIZE, "surface", colored=True).render(
        mass_field(x, m_p, N_GRID, DENSITY, colors)).astype(int)
    left = distances(CENTER - 0.6 * RADIUS * right_axis) < 3
    right = distances(CENTER + 0.6 * RADIUS * right_axis) < 3
    assert (img[left][:, 0] > img[left][:, 2] + 60).all() and (img[right][:, 2] > img[right][:, 0] + 60).all()
    assert (img[left][:, 1] < 10).all()


def test_particles_are_spheres_and_the_nearest_shows():
    near, far = CENTER + 0.1 * camera()[0], CENTER - 0.1 * camera()[0]  # on one ray, near nearer the camera
    x = np.array([far, near])
    colors = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    preview = Preview3D(N_GRID, SIZE, "particles", colored=True, spacing=0.1)
    img = preview.render(None, x, colors).astype(int)
    dist = distances(CENTER)
    drawn = np.any(img != 255, axis=2)
    assert np.array_equal(drawn, dist <= preview.radius)
    assert (img[drawn][:, 1] > 0).all() and (img[drawn][:, [0, 2]] == 0).all()  # the near one: green
    assert img[dist < 1][:, 1].min() > img[drawn][:, 1].min()  # lit most where the sphere faces the light
    plain = Preview3D(N_GRID, SIZE, "particles", spacing=0.1).render(None, x[::-1], colors).astype(int)
    r, g, b = plain[drawn].T
    assert (r > 4 * g).all() and (g == b).all() and r.max() > 150  # BODY_COLOR (red), in any order


def test_the_target_silhouette_is_outlined_in_black():
    x, m_p = ball(radius=0.2)
    target = mass_field(x, m_p, N_GRID, DENSITY).t
    img = Preview3D(N_GRID, SIZE, "surface").render(MassField(np.zeros((N_GRID,) * 3), None, DENSITY),
                                                    target=target).astype(int)
    inked = np.any(img != 255, axis=2)  # the antialiased line, and nothing else (no body)
    dist = distances(CENTER)
    assert (np.abs(dist[inked] - pixel_radius(0.2)) < pixel_radius(0.6 * DX)).all()  # the ball's level-1/2 silhouette
    assert np.count_nonzero(inked) > 2 * np.pi * pixel_radius(0.2)  # all around the circle
    assert img.min() < 60 and (img[inked][:, 0] == img[inked][:, 1]).all()  # black (grey where partly covered)
