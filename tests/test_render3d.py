"""The 3D preview (mls_mpm/render3d.py): camera, the surface and volume ray marchers, particle spheres and the
target's silhouette, checked on pixel values of small frames of a ball built from numpy arrays."""
import numpy as np
import pytest
import taichi as ti

from mls_mpm.field3d import MassField, mass_field
from mls_mpm.render3d import (ROOT_STEPS, Preview3D, camera, cell_corners, cell_cubic, cubic_at, first_crossing,
                              project, trilinear_at)

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


def sheet_crossings(plane):
    """(y, z) in cells where each pixel's ray crosses the plane x = plane (in cells)."""
    d, right, up, half = camera()
    c, r = np.meshgrid(np.arange(SIZE) + 0.5, np.arange(SIZE) + 0.5)
    u, v = (2 * c / SIZE - 1) * half, (1 - 2 * r / SIZE) * half
    o = CENTER + u[..., None] * right + v[..., None] * up
    at = o - ((o[..., 0] - plane * DX) / d[0])[..., None] * d  # along the ray, on the plane
    return at[..., 1] / DX, at[..., 2] / DX


@pytest.mark.parametrize("peak", [0.52, 0.9])
def test_a_thin_sheet_shows_without_gaps(peak):
    """One layer of nodes x = 8 cells, y and z 4..11, at t = peak (a thin or stretched part: t reaches the surface
    level 1/2 only within 1 - 1/(2 peak) cells of the layer, 0.04 cells at 0.52). The surface mode draws every pixel
    whose ray crosses the layer where its interpolant is peak (y and z 4..11, half a cell in from the edge) and none
    whose ray crosses the plane more than 1.5 cells (the ray's sideways travel through the layer) outside it. The
    march by half-cell steps before render3d's exact one missed the layer at 0.52 on every ray (305 of 305)."""
    t = np.zeros((N_GRID,) * 3)
    t[8, 4:12, 4:12] = peak
    img = Preview3D(N_GRID, SIZE, "surface").render(MassField(t * DENSITY / N_GRID ** 3, None, DENSITY))
    drawn = np.any(img != 255, axis=2)
    y, z = sheet_crossings(8)
    inside = (np.minimum(y, z) > 4.5) & (np.maximum(y, z) < 10.5)
    outside = (np.minimum(y, z) < 2.5) | (np.maximum(y, z) > 12.5)
    assert np.count_nonzero(inside) > 200
    assert drawn[inside].all(), f"{np.count_nonzero(~drawn[inside])} of {np.count_nonzero(inside)} pixels missed"
    assert not drawn[outside].any()


def test_a_thin_target_sheet_is_outlined():
    """The target silhouette (peak_along_rays) of the thin layer of test_a_thin_sheet_shows_without_gaps at t = 0.52:
    the outline runs along the patch's edge, where the rays cross the plane within 1.5 cells of y or z = 4 or 11, and
    all around it. The half-cell samples before the exact peak read it above 1/2 on some rays and below on others:
    stripes of outline across the patch (103 of 303 inked pixels away from its edge)."""
    t = np.zeros((N_GRID,) * 3)
    t[8, 4:12, 4:12] = 0.52
    img = Preview3D(N_GRID, SIZE, "surface").render(MassField(np.zeros((N_GRID,) * 3), None, DENSITY), target=t)
    inked = np.any(img != 255, axis=2)
    y, z = sheet_crossings(8)
    edge = np.minimum(np.minimum(np.abs(y - 4), np.abs(y - 11)), np.minimum(np.abs(z - 4), np.abs(z - 11)))
    patch = (np.minimum(y, z) > 4) & (np.maximum(y, z) < 11)
    assert (edge[inked] < 1.5).all()
    ring = patch & (edge < 1)  # the patch's rim: each side of it inked somewhere
    for side in (y < 5, y > 10, z < 5, z > 10):
        assert inked[ring & side].any()
    assert np.count_nonzero(inked) > 40


@ti.kernel
def crossings(k: ti.types.ndarray(), iso: float, length: ti.types.ndarray(), out: ti.types.ndarray()):
    for j in range(out.shape[0]):
        out[j] = first_crossing(ti.Vector([k[j, 0], k[j, 1], k[j, 2], k[j, 3]]), iso, length[j])


def test_first_crossing_is_the_first_root_of_the_cubic():
    """render3d.first_crossing (a cell's surface hit) against numpy's roots of k(s) - iso: on random cubics over
    random lengths, the least root in [0, length] where the cubic rises through iso, within the bracket the
    bisection leaves (length / 2^ROOT_STEPS); -1 where there is none. Cubics that only touch iso (a double root) or
    cross it within 1e-6 of an end are left out: there the answer is a matter of round-off."""
    rng = np.random.default_rng(3)
    n, iso = 4000, 0.5
    k = rng.normal(size=(n, 4)) * [0.4, 1.5, 3.0, 3.0] + [0.2, 0, 0, 0]
    length = rng.uniform(0.05, 1.8, n)
    expect = np.full(n, -1.0)
    keep = np.ones(n, bool)
    for j in range(n):
        roots = np.roots([k[j, 3], k[j, 2], k[j, 1], k[j, 0] - iso])
        real = np.sort(roots[np.abs(roots.imag) < 1e-9].real)
        near = np.abs(np.diff(real)).min() < 1e-4 if len(real) > 1 else False
        edge = (np.abs(real) < 1e-6).any() or (np.abs(real - length[j]) < 1e-6).any()
        keep[j] = not (near or edge)
        if k[j, 0] >= iso:
            expect[j] = 0.0
        else:
            inside = real[(real >= 0) & (real <= length[j])]
            expect[j] = inside[0] if len(inside) else -1.0
    out = np.zeros(n)
    crossings(k, iso, length, out)
    assert 0.2 < np.mean(expect[keep] > 0) < 0.8 and np.mean(expect[keep] == 0) > 0.05  # both kinds occur
    err = np.abs(out - expect)[keep]
    assert (err <= length[keep] * 2.0 ** -ROOT_STEPS).all(), err.max()
    assert ((out < 0) == (expect < 0)).all()  # a hit where there is one, and none elsewhere


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


# -- a whole 3D render (render_run) of a positions-method result, which needs no simulation ----------------------

def fake_3d_result(n_particles_axis=2):
    """(meta, arrays) of a 3D result of the positions method (frames: the sampled ball, then final_x, a shifted
    ball), as load_result returns them."""
    from mls_mpm.field3d import splat

    x, m_p = ball(radius=0.2, k=n_particles_axis)
    N = len(x)
    sim = dict(dim=3, n_grid=N_GRID, steps=10, dt=1e-3, E=100.0, nu=0.3, density=DENSITY, gamma=0.0,
               gravity=[0.0, 0.0, 0.0], boundary="slip", bound=3, particles_per_cell=n_particles_axis ** 3,
               dtype="f64", arch="cpu")
    settings = dict(scene=dict(name="ball3d", target_density="match"), sim=sim, control=dict(stride=5),
                    loss=dict(kind="mass"), render=dict(mode="mass", size=64, every=5, gif=True, outline=True))
    target = x + [0.1, 0.0, 0.0]
    arrays = dict(controls=np.zeros((1, 2, N, 3, 3)), colors=np.tile([0.9, 0.6, 0.1], (N, 1)), init_x=x[None],
                  init_v=np.zeros((1, N, 3)), init_C=np.zeros((1, N, 3, 3)), init_F=np.tile(np.eye(3), (1, N, 1, 1)),
                  target_grid=splat(target, m_p, N_GRID)[0], final_x=target, losses=np.array([1.0, 0.5]),
                  round_lengths=np.array([2]), target_points=target, target_colors=np.tile([0.2, 0.2, 0.9], (N, 1)))
    return dict(settings=settings, method="positions"), arrays


def test_a_3d_run_renders_frames_particles_meshes_and_videos(tmp_path, monkeypatch):
    from mls_mpm import render_run as rr
    from mls_mpm.export3d import read_ply
    from mls_mpm.frames import frame_paths
    from mls_mpm.video import read_mp4
    from PIL import Image

    meta, arrays = fake_3d_result()
    monkeypatch.setattr(rr, "load_result", lambda out: (meta, arrays))
    lines = []
    paths = rr.render_run(tmp_path, emit=lines.append)
    assert [p.name for p in paths] == ["frame_00000.png", "frame_00001.png"]
    for folder in ("particles", "meshes"):
        assert sorted(p.name for p in (tmp_path / folder).iterdir()) == ["frame_00000.ply", "frame_00001.ply"]
        assert not (tmp_path / f"{folder}.new").exists() and not (tmp_path / f"{folder}.old").exists()
    first = read_ply(tmp_path / "particles" / "frame_00000.ply")["vertex"]
    np.testing.assert_array_equal(np.stack([first["x"], first["y"], first["z"]], 1),
                                  arrays["init_x"][0].astype(np.float32))
    last = read_ply(tmp_path / "particles" / "frame_00001.ply")["vertex"]
    np.testing.assert_array_equal(last["x"], arrays["final_x"][:, 0].astype(np.float32))
    assert (last["red"] == 230).all() and np.median(last["density"]) == pytest.approx(DENSITY, rel=0.3)
    mesh = read_ply(tmp_path / "meshes" / "frame_00001.ply")
    v = np.stack([mesh["vertex"]["x"], mesh["vertex"]["y"], mesh["vertex"]["z"]], 1)
    assert len(mesh["face"]) > 50 and np.abs(v.mean(axis=0) - [0.6, 0.5, 0.5]).max() < 0.02  # the moved ball
    frame = np.asarray(Image.open(paths[0]))
    assert frame.shape == (64, 64, 3) and frame[32, 32, 0] > frame[32, 32, 1] + 40  # the ball, red (at rest)
    assert read_mp4(tmp_path / "animation.mp4") == (2, (64, 64))
    for name in ("animation.gif", "sheet.png", "loss.png"):
        assert (tmp_path / name).is_file()
    assert lines[1].startswith(f"wrote 2 frames to {tmp_path / 'frames'} and as many to")
    assert lines[2].startswith("per frame: simulation ") and " mesh " in lines[2]
    with pytest.raises(rr.RenderError, match=r"^--mode mass: expected one of surface, volume, particles \(a 3D run\)"):
        rr.render_run(tmp_path, mode="mass", emit=lines.append)


@ti.kernel
def along_cell(grid: ti.template(), i: ti.types.vector(3, ti.i32), o: ti.types.vector(3, float),
               dirn: ti.types.vector(3, float), s: float, inv_dx: float, ds: ti.types.ndarray(),
               out: ti.types.ndarray()):
    k = cell_cubic(cell_corners(grid, i), o, dirn, s, i, inv_dx)
    for j in range(ds.shape[0]):
        out[j, 0] = cubic_at(k, ds[j])
        out[j, 1] = trilinear_at(grid, o + (s + ds[j]) * dirn, inv_dx)


def test_cell_cubic_is_the_trilinear_field_along_the_ray():
    """render3d.cell_cubic (the interpolant along a ray in one cell, as a cubic) against render3d.trilinear_at (the
    field interpolated at each point) on random corner values and random rays through a cell, at points spread
    over the cell's span of the ray: equal to 1e-9 (float64)."""
    rng = np.random.default_rng(5)
    n, inv_dx = 4, 4.0
    grid = ti.field(ti.f64, (n, n, n))
    grid.from_numpy(rng.uniform(0, 2, (n, n, n)))
    for _ in range(20):
        cell = rng.integers(0, n - 1, 3)
        p = (cell + rng.uniform(0, 1, 3)) / inv_dx  # a point in the cell
        dirn = rng.normal(size=3)
        dirn /= np.linalg.norm(dirn)
        s = rng.uniform(-1, 1)  # the ray's parameter at p: o = p - s dirn
        lo = (cell / inv_dx - p) / dirn  # the ray's span in the cell about p, per axis
        hi = ((cell + 1) / inv_dx - p) / dirn
        span = (np.minimum(lo, hi).max(), np.maximum(lo, hi).min())
        ds = np.linspace(span[0] + 1e-6, span[1] - 1e-6, 9)  # inside: at a face of the grid trilinear_at jumps
        out = np.zeros((9, 2))
        along_cell(grid, cell.astype(np.int32), p - s * dirn, dirn, s, inv_dx, ds, out)
        assert np.abs(out[:, 0] - out[:, 1]).max() < 1e-9, (cell, out)
        assert np.ptp(out[:, 1]) > 1e-3  # the field varies along the ray: the check has teeth
