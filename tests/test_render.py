"""Renderers (thesis 7.1, 7.5, Fig 3) and frame output: pixel values, orientation, files."""
import numpy as np
import pytest
import taichi as ti
from PIL import Image
from scipy import ndimage

import mls_mpm
import mls_mpm.runtime
from mls_mpm.frames import FrameWriter, frame_paths, loss_plot, sheet, write_gif
from mls_mpm.colormap import PATH, Thresholds, path_color, path_position
from mls_mpm.contour import contour, draw_outline
from mls_mpm.render import BODY_OUTLINE_COLOR, TARGET_COLOR, Renderer, estimate_bytes

N_GRID = 32
DX = 1.0 / N_GRID
REST = DX * DX  # density 1: rest node mass density * dx^2
SIZE = 96
WHITE = [255, 255, 255]
RED = [255, 0, 0]


@pytest.fixture(scope="module", autouse=True)
def taichi():
    mls_mpm.runtime.ensure(mls_mpm.SimConfig(dtype="f64"))


def block(lo, hi, ppc_axis=2):
    """Particles filling [lo, hi)^2 at ppc_axis^2 per cell, evenly spaced, with the rest-density mass."""
    cells = round((hi - lo) / DX)
    s = lo + (np.arange(cells * ppc_axis) + 0.5) * DX / ppc_axis
    x = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
    return x, REST / ppc_axis ** 2


def pixel_rect(lo, hi):
    """Row and column slices of the pixels whose centers lie in [lo, hi)^2 of the domain."""
    c0, c1 = int(np.ceil(lo * SIZE - 0.5)), int(np.ceil(hi * SIZE - 0.5))
    r0, r1 = SIZE - c1, SIZE - c0  # rows count down from y = 1
    return slice(r0, r1), slice(c0, c1)


def recovered_position(rgb):
    """Position along the white -> blue -> green -> red path of uint8 colors (inverse of the palette)."""
    c = rgb.astype(np.float64) / 255.0
    pts = np.array(PATH)
    best_d, best_s = np.full(len(c), np.inf), np.zeros(len(c))
    for k in range(3):
        a, b = pts[k], pts[k + 1]
        u = np.clip(((c - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
        d = np.linalg.norm(c - (a + u[:, None] * (b - a)), axis=1)
        better = d < best_d
        best_d[better], best_s[better] = d[better], k + u[better]
    assert best_d.max() < 0.01, "a rendered color lies off the colormap path"
    return best_s


@pytest.mark.parametrize("mode", ["mass", "color", "particles"])
def test_empty_domain_is_white(mode):
    r = Renderer(N_GRID, 0, SIZE, REST, mode, body_outline=True)
    img = r.render(np.zeros((0, 2)), REST / 4, colors=np.zeros((0, 3)))
    assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
    assert (img == 255).all()


def test_rest_block_is_red_inside_and_white_far_outside():
    x, m_p = block(0.25, 0.75)
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass")
    img = r.render(x, m_p)
    # P2G and sampling each reach 2 cells; 4 cells inside, the sampled mass is exactly the rest node mass
    rows, cols = pixel_rect(0.25 + 4 * DX, 0.75 - 4 * DX)
    np.testing.assert_allclose(r.pixel_m.to_numpy()[rows, cols], 1.0, atol=1e-9)
    assert (img[rows, cols] == RED).all()
    outside = np.ones((SIZE, SIZE), bool)
    rows, cols = pixel_rect(0.25 - 4 * DX, 0.75 + 4 * DX)
    outside[rows, cols] = False
    assert (img[outside] == WHITE).all()
    # the fade from red to white at the edge passes through every color of the path
    s = recovered_position(img.reshape(-1, 3))
    assert s.min() == 0.0 and s.max() == 3.0 and np.any((s > 0.9) & (s < 1.1)) and np.any((s > 1.9) & (s < 2.1))


@pytest.mark.parametrize("mode", ["mass", "color", "particles"])
def test_a_transparent_background_is_alpha_0_and_the_body_opaque(mode, tmp_path):
    x, m_p = block(0.25, 0.75)
    colors = np.tile([0.2, 0.4, 0.9], (len(x), 1))
    target = np.zeros((N_GRID, N_GRID))
    target[8:24, 8:24] = REST  # an outline through the background too
    white = Renderer(N_GRID, len(x), SIZE, REST, mode).render(x, m_p, colors=colors, target_outline=target)
    clear = Renderer(N_GRID, len(x), SIZE, REST, mode, background="transparent")
    img = clear.render(x, m_p, colors=colors, target_outline=target)
    assert img.shape == (SIZE, SIZE, 4) and img.dtype == np.uint8
    assert img[0, 0, 3] == 0 and img[SIZE // 2, SIZE // 2, 3] == 255  # a corner, the body's centre
    assert (img[..., 3] == 0).sum() > SIZE * SIZE // 4  # most of the background
    np.testing.assert_array_equal(img[..., :3], white)  # composited on white: the white frame
    assert set(np.unique(img[..., 3])) == {0, 255}
    path = FrameWriter(tmp_path).write(img)
    with Image.open(path) as im:
        assert im.mode == "RGBA" and np.array_equal(np.asarray(im), img)


def test_mass_colormap_is_monotone_with_documented_anchors():
    th = Thresholds()
    r = Renderer(N_GRID, 0, SIZE, REST, "mass", thresholds=th)
    t = np.linspace(0.0, 2.0, 4001)
    s, rgb = r.colormap(t)
    assert np.all(np.diff(s) >= 0.0)
    np.testing.assert_allclose(s, path_position(t, th), atol=1e-12)
    np.testing.assert_array_equal(rgb, np.floor(path_color(s) * 255.0 + 0.5).astype(np.uint8))
    assert np.all(np.diff(recovered_position(rgb)) >= -1.0 / 255.0)  # monotone up to the rounding to bytes
    anchors = [0.0, th.empty, th.low, th.mid, th.high, 5.0]
    _, rgb = r.colormap(anchors)
    np.testing.assert_array_equal(rgb, [WHITE, WHITE, [0, 0, 255], [0, 255, 0], RED, RED])


def test_rendered_mass_colors_are_monotone_in_sampled_mass():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.2, 0.8, size=(3000, 2))  # an irregular cloud: masses from zero to above rest
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass")
    img = r.render(x, REST / 4 * rng.uniform(0.5, 2.0, size=len(x)))
    m = r.pixel_m.to_numpy().ravel()
    assert m.max() > 1.0 and m.min() < 1e-3
    s = recovered_position(img.reshape(-1, 3)[np.argsort(m, kind="stable")])
    assert np.all(np.diff(s) >= -1.0 / 255.0)


def test_color_field_of_red_body_is_red_inside():
    x, m_p = block(0.25, 0.75)
    r = Renderer(N_GRID, len(x), SIZE, REST, "color")
    img = r.render(x, m_p, colors=np.tile([1.0, 0.0, 0.0], (len(x), 1)))
    rows, cols = pixel_rect(0.25 + 4 * DX, 0.75 - 4 * DX)
    assert (img[rows, cols] == RED).all()
    assert (img[0] == WHITE).all() and (img[:, -1] == WHITE).all()
    # near the edge the color fades to white along red's own line: G and B stay equal, R stays 255
    edge = img[(img != 255).any(-1)]
    assert (edge[:, 0] == 255).all() and (edge[:, 1] == edge[:, 2]).all()


def test_color_field_two_halves():
    x, m_p = block(0.125, 0.875)
    colors = np.where(x[:, :1] < 0.5, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    r = Renderer(N_GRID, len(x), SIZE, REST, "color")
    img = r.render(x, m_p, colors=(colors * 255).astype(np.uint8))
    rows, left = pixel_rect(0.125 + 4 * DX, 0.5 - 4 * DX)  # 4 cells from the body's edge and the interface
    _, right = pixel_rect(0.5 + 4 * DX, 0.875 - 4 * DX)
    assert (img[rows, left] == RED).all() and (img[rows, right] == [0, 0, 255]).all()


@pytest.mark.parametrize("mode", ["mass", "particles"])
def test_y_axis_points_up(mode):
    x, m_p = block(0.75, 0.875)  # top-right corner of the domain
    r = Renderer(N_GRID, len(x), SIZE, REST, mode)
    img = r.render(x, m_p)
    rows, cols = np.nonzero((img != 255).any(-1))
    assert len(rows) and rows.max() < SIZE // 2 and cols.min() >= SIZE // 2
    assert (img[SIZE - 12, SIZE - 12] == WHITE).all() and (img[12, SIZE - 12] != WHITE).any()


def test_particles_ellipses_follow_F_and_targets_are_green():
    x = np.array([[0.3, 0.5]])
    target = np.array([[0.7, 0.5]])
    r = Renderer(N_GRID, 1, SIZE, REST, "particles", radius=3.0)
    F = np.array([[[3.0, 0.0], [0.0, 1.0]]])  # stretched along x: a 9 x 3 pixel half-axis ellipse
    img = r.render(x, REST, F=F, target_x=target)
    body = (img == r.render(x, REST)[int(SIZE / 2), int(0.3 * SIZE)]).all(-1)
    rows, cols = np.nonzero(body)
    assert 15 <= cols.max() - cols.min() + 1 <= 19 and 4 <= rows.max() - rows.min() + 1 <= 7
    green = (img == np.floor(np.array(TARGET_COLOR) * 255 + 0.5).astype(np.uint8)).all(-1)
    rows, cols = np.nonzero(green)
    assert len(rows) and abs(cols.mean() + 0.5 - 0.7 * SIZE) < 1.0 and abs(rows.mean() + 0.5 - 0.5 * SIZE) < 1.0


def bspline(t):
    """The 1D cubic B-spline N1 (eq 2), numpy reference."""
    t = np.abs(t)
    return np.where(t < 1.0, 0.5 * t ** 3 - t ** 2 + 2.0 / 3.0, np.where(t < 2.0, (2.0 - t) ** 3 / 6.0, 0.0))


def sampled(grid, size):
    """sum_i N(x - x_i) g_i at every pixel center [row, column] of a (n, n, ...) grid: the direct 16-node sum."""
    n = grid.shape[0]
    centers = (np.arange(size) + 0.5) / size
    wx = bspline(centers[:, None] * n - np.arange(n))  # [column, i]
    wy = bspline((1.0 - centers)[:, None] * n - np.arange(n))  # [row, j]
    return np.einsum("rj,ij...,ci->rc...", wy, grid, wx)


def irregular_cloud(rng, count):
    """Particles over the whole domain, border cells included (their stencils reach off the grid)."""
    return np.concatenate([rng.uniform(0.2, 0.8, size=(count, 2)), rng.uniform(0.0, 1.0, size=(count // 4, 2))])


def test_separable_sampling_matches_the_direct_sum():
    rng = np.random.default_rng(1)
    x = irregular_cloud(rng, 3000)
    m_p = REST / 4 * rng.uniform(0.5, 2.0, size=len(x))
    for size in (SIZE, 77):  # pixel centers on and off the grid lines
        r = Renderer(N_GRID, len(x), size, REST, "mass")
        r.render(x, m_p)
        grid = r.grid_m.to_numpy()
        np.testing.assert_allclose(r.pixel_m.to_numpy(), sampled(grid, size) / REST, rtol=0, atol=1e-12)


def test_mass_and_color_pixels_match_numpy_reference():
    rng = np.random.default_rng(2)
    x = irregular_cloud(rng, 3000)
    m_p = REST / 4 * rng.uniform(0.5, 2.0, size=len(x))
    colors = rng.uniform(0.0, 1.0, size=(len(x), 3))
    th = Thresholds()
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass")
    img = r.render(x, m_p)
    t = sampled(r.grid_m.to_numpy(), SIZE) / REST
    want = np.floor(path_color(path_position(t, th)) * 255.0 + 0.5)
    assert np.abs(img - want).max() <= 1 and (img == want).mean() > 0.999  # bytes differ only at rounding ties

    r = Renderer(N_GRID, len(x), SIZE, REST, "color")
    img = r.render(x, m_p, colors=colors)
    m = sampled(r.grid_m.to_numpy(), SIZE)
    c = sampled(r.grid_c.to_numpy(), SIZE)
    t = m / REST
    a = np.clip((t - th.empty) / (th.low - th.empty), 0.0, 1.0)[..., None]
    rgb = np.clip(c / np.maximum(m, 1e-300)[..., None], 0.0, 1.0)
    want = np.floor(np.where(t[..., None] > th.empty, 1.0 - a + rgb * a, 1.0) * 255.0 + 0.5)
    assert np.abs(img - want).max() <= 1 and (img == want).mean() > 0.999


def test_frames_are_independent_and_reproducible():
    rng = np.random.default_rng(3)
    x = irregular_cloud(rng, 2000)
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass")
    first = r.render(x, REST / 4)
    kept = first.copy()
    second = r.render(x, REST / 4)
    assert second is not first and np.array_equal(first, kept)  # a new frame does not overwrite the last one
    np.testing.assert_array_equal(first, second)  # the splat adds in particle order: same bytes every time
    assert not np.array_equal(r.render(x[:1000], REST / 4), first)


# -- outlines: marching squares on the pixel samples -----------------------------------------------------
def pixel_field(values):
    """A Taichi field holding a numpy array [row, column] (the kernels' pixel fields are Taichi fields)."""
    f = ti.field(float, shape=values.shape)
    f.from_numpy(np.asarray(values, dtype=np.float64))
    return f


def ink_of(values, level, width, background=None):
    """(the image with the outline drawn in black, its coverage 1 - byte / 255 over white) of a pixel field."""
    f = pixel_field(values)
    field = ti.Vector.field(3, ti.u8, shape=values.shape)  # the Renderer's kernels draw into a Taichi field
    field.from_numpy(np.full(values.shape + (3,), 255, np.uint8) if background is None else background)
    draw_outline(f, ti.field(float, shape=values.shape), field, level, float(width), ti.Vector([0.0, 0.0, 0.0]))
    image = field.to_numpy()
    return image, 1.0 - image[..., 0] / 255.0


def centers(shape):
    """(u, v): continuous pixel coordinates (column, row) of every pixel center."""
    return np.meshgrid(np.arange(shape[1]) + 0.5, np.arange(shape[0]) + 0.5)


def distance_to_segments(points, segments):
    """Distance of each point (P, 2) to the nearest of segments (K, 2, 2), brute force."""
    a, ab = segments[:, 0], segments[:, 1] - segments[:, 0]
    q = points[:, None, :] - a[None]
    s = np.clip((q * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(q - s[..., None] * ab, axis=-1).min(axis=1)


def edge_value(values, points):
    """The field at points on cell edges, interpolated linearly along the edge between its two samples."""
    u, v = points[:, 0] - 0.5, points[:, 1] - 0.5
    r0, c0 = np.floor(v).astype(int), np.floor(u).astype(int)
    r1, c1 = np.minimum(r0 + 1, values.shape[0] - 1), np.minimum(c0 + 1, values.shape[1] - 1)
    fr, fc = v - r0, u - c0
    assert np.all((np.abs(fr) < 1e-9) | (np.abs(fc) < 1e-9)), "a segment endpoint lies inside a cell"
    return (values[r0, c0] * (1 - fr) * (1 - fc) + values[r1, c0] * fr * (1 - fc) + values[r0, c1] * (1 - fr) * fc
            + values[r1, c1] * fr * fc)


@pytest.mark.parametrize("width", [1, 2, 3])
def test_outline_of_a_disk_follows_the_circle(width):
    """f = 1 - (rho / 40)^2 around an off-grid center: the contour f = 7/16 is the circle rho = 30."""
    shape, center, radius = (96, 96), np.array([48.3, 47.6]), 30.0
    u, v = centers(shape)
    rho = np.hypot(u - center[0], v - center[1])
    values = 1.0 - (rho / 40.0) ** 2
    level = 1.0 - (radius / 40.0) ** 2
    seg = contour(pixel_field(values), level)
    on = lambda p: np.abs(np.linalg.norm(p - center, axis=-1) - radius)  # distance to the true circle
    # endpoints interpolated along the edges lie on the circle to 0.02 px (edge midpoints would be 0.5 px off),
    # and so do the chords between them
    assert len(seg) > 2 * np.pi * radius and on(seg).max() < 0.02 and on(seg.mean(axis=1)).max() < 0.02
    # a closed curve: every endpoint is shared by exactly two segments
    _, uses = np.unique(np.round(seg.reshape(-1, 2), 6), axis=0, return_counts=True)
    assert (uses == 2).all()

    image, cov = ink_of(values, level, width)
    drawn = cov > 0
    assert (image == image[..., :1]).all()  # black on white: grey levels only
    assert np.abs(rho[drawn] - radius).max() <= width / 2 + 1
    # antialiased: each pixel's coverage is clamp(width/2 + 1/2 - d, 0, 1), d its distance to the circle
    want = np.clip(width / 2 + 0.5 - np.abs(rho - radius), 0.0, 1.0)
    assert np.abs(cov - want).max() < 0.02
    assert np.any((cov > 0.1) & (cov < 0.9))
    # no gap: at every angle the pixel the circle passes through is inked, at least as much as a pixel center
    # sqrt(2) / 2 from the line
    t = np.linspace(0.0, 2 * np.pi, 3600, endpoint=False)
    col, row = np.floor(center[:, None] + radius * np.stack([np.cos(t), np.sin(t)])).astype(int)
    assert cov[row, col].min() >= min(width / 2 + 0.5 - np.sqrt(0.5), 1.0) - 0.02


def segment_set(seg):
    """Segments (K, 2, 2) as a sorted list of endpoint pairs, each pair sorted, rounded to 1e-9."""
    return sorted(tuple(sorted(tuple(np.round(p, 9)) for p in s)) for s in seg)


@pytest.mark.parametrize("values, level, want", [
    # corners 0 (row 0, column 0) and 2 inside; center average 0.5 below 0.6: the inside corners stay apart
    ([[1.0, 0.0], [0.0, 1.0]], 0.6, [[(0.5, 0.9), (0.9, 0.5)], [(1.1, 1.5), (1.5, 1.1)]]),
    # ... at or above the level: the inside corners join, the segments cut off the outside corners 1 and 3
    ([[1.0, 0.0], [0.0, 1.0]], 0.4, [[(0.5, 1.1), (0.9, 1.5)], [(1.1, 0.5), (1.5, 0.9)]]),
    ([[1.0, 0.0], [0.0, 1.0]], 0.5, [[(0.5, 1.0), (1.0, 1.5)], [(1.0, 0.5), (1.5, 1.0)]]),
    # the other saddle, corners 1 and 3 inside
    ([[0.0, 1.0], [1.0, 0.0]], 0.6, [[(0.5, 1.1), (0.9, 1.5)], [(1.1, 0.5), (1.5, 0.9)]]),
    ([[0.0, 1.0], [1.0, 0.0]], 0.4, [[(0.5, 0.9), (0.9, 0.5)], [(1.1, 1.5), (1.5, 1.1)]]),
])
def test_saddle_cells_are_resolved_by_the_center_average(values, level, want):
    """Pixel samples at (column + 1/2, row + 1/2); endpoints interpolate linearly along the cell edges."""
    seg = contour(pixel_field(np.array(values)), level)
    assert segment_set(seg) == segment_set(np.array(want))


@pytest.mark.parametrize("value", [0.0, 0.5, 1.0])
def test_a_field_on_one_side_of_the_level_draws_nothing(value):
    values = np.full((24, 24), value)  # level 0.5: below, exactly at (inside) and above
    background = np.random.default_rng(4).integers(0, 256, size=(24, 24, 3), dtype=np.uint8)
    image, _ = ink_of(values, 0.5, 3, background)
    np.testing.assert_array_equal(image, background)
    assert contour(pixel_field(values), 0.5).shape == (0, 2, 2)


@pytest.mark.parametrize("width", [1, 3])
def test_body_outline_surrounds_the_colored_pixels(width):
    x, m_p = block(0.375, 0.625)
    plain = Renderer(N_GRID, len(x), SIZE, REST, "mass").render(x, m_p)
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass", body_outline=True, line_width=width)
    img = r.render(x, m_p)
    m, ink = r.pixel_m.to_numpy(), r.ink.to_numpy()
    level = Thresholds().empty
    colored = m > level  # the pixels the colormap paints (those just above may still round to white)
    assert (img[SIZE // 2, SIZE // 2] == RED).all() and not ((plain != 255).any(-1) & ~colored).any()
    # the outline changes only the pixels it inks, and those fully inked take its color
    changed = (img != plain).any(-1)
    assert changed.sum() > 4 * 0.25 * SIZE and not (changed & (ink == 0)).any()
    grey = np.floor(np.array(BODY_OUTLINE_COLOR) * 255 + 0.5).astype(np.uint8)
    assert (img[ink == 1.0] == grey).all() and (ink == 1.0).sum() >= (changed.sum() if width == 3 else 1) // 3
    # it is the contour m(x) / rest = empty: endpoints at that level, inked pixels within reach of a segment
    seg = contour(r.pixel_m, level)
    np.testing.assert_allclose(edge_value(m, seg.reshape(-1, 2)), level, rtol=0, atol=1e-12)
    u, v = centers(m.shape)
    points = np.stack([u[ink > 0], v[ink > 0]], -1)
    assert distance_to_segments(points, seg).max() < width / 2 + 0.5
    # it surrounds the colored pixels: every colored pixel next to a white one is inked, so no path of uninked
    # pixels leads from the image border to a colored pixel
    regions, _ = ndimage.label(ink == 0)  # 4-connected
    outside = np.unique(np.concatenate([regions[0], regions[-1], regions[:, 0], regions[:, -1]]))
    reached = np.isin(regions, outside[outside > 0])
    assert reached.sum() > SIZE * SIZE / 2 and not (reached & colored).any()
    np.testing.assert_array_equal(r.render(x, m_p), img)  # ink is a maximum: the same bytes in any cell order


def test_target_outline_lies_on_the_level_set_of_the_target_field():
    res = 2 * N_GRID  # a finer target grid (thesis 8.1)
    target = np.zeros((res, res))
    target[res // 4: 3 * res // 4 + 1, res // 4: 3 * res // 4 + 1] = (1.0 / res) ** 2  # rest mass of its nodes
    r = Renderer(N_GRID, 0, SIZE, REST, "mass", line_width=2)
    img = r.render_target(target)
    f, ink = sampled(target, SIZE) / (1.0 / res) ** 2, r.ink.to_numpy()  # the target field, numpy reference
    seg = contour(pixel_field(f), r.target_level)
    np.testing.assert_allclose(edge_value(f, seg.reshape(-1, 2)), r.target_level, rtol=0, atol=1e-12)
    # nodes 16..48 of 64 hold mass: the B-spline-smoothed field is 1/2 halfway to the empty nodes 15 and 49,
    # x = 15.5 / 64 and 48.5 / 64, and so is the contour along the sides (the corners are rounded)
    lo, hi = 15.5 / res * SIZE, 48.5 / res * SIZE
    assert abs(seg[..., 0].min() - lo) < 0.05 and abs(seg[..., 0].max() - hi) < 0.05
    assert abs(seg[..., 1].min() - (SIZE - hi)) < 0.05 and abs(seg[..., 1].max() - (SIZE - lo)) < 0.05
    plain = r.render_target(target, outline=False)
    changed = (img != plain).any(-1)
    u, v = centers(f.shape)
    assert changed.sum() > 4 * 0.4 * SIZE and not (changed & (ink == 0)).any()
    assert distance_to_segments(np.stack([u[changed], v[changed]], -1), seg).max() < 2 / 2 + 0.5
    assert (img[ink == 1.0] == 0).all() and (ink == 1.0).any()  # black where fully covered
    # over any view: the same outline over an empty mass frame, blended from white by its coverage
    frame = r.render(np.zeros((0, 2)), REST, target_outline=target)
    np.testing.assert_array_equal(r.ink.to_numpy(), ink)
    assert np.abs(frame.astype(int) - np.floor(255.0 * (1.0 - ink) + 0.5)[..., None]).max() <= 1


def test_render_target_matches_rendered_particles():
    x, m_p = block(0.25, 0.75)
    r = Renderer(N_GRID, len(x), SIZE, REST, "mass")
    img = r.render(x, m_p)
    grid = r.grid_m.to_numpy()
    np.testing.assert_array_equal(r.render_target(grid, outline=False), img)


def allocated_bytes(value):
    """Bytes held by the Taichi fields and numpy arrays in value (an object's attributes, a tuple, ...)."""
    if isinstance(value, ti.Field):
        return value.to_numpy().nbytes
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return sum(allocated_bytes(v) for v in value)
    return 0


@pytest.mark.parametrize("mode", ["mass", "color", "particles"])
def test_memory_estimate_is_what_a_renderer_allocates(mode):
    """render_run refuses a renderer that would not fit by estimate_bytes, before building it: the estimate
    must be the bytes of the fields and buffers the Renderer then holds, plus the frame it returns."""
    x, m_p = block(0.25, 0.75)
    target = np.zeros((48, 48))
    target[12:36, 12:36] = (1.0 / 48) ** 2
    r = Renderer(N_GRID, len(x), 80, REST, mode, body_outline=True)
    frame = r.render(x, m_p, colors=np.ones((len(x), 3)), target_outline=target)
    held = sum(allocated_bytes(v) for v in vars(r).values())
    assert estimate_bytes(N_GRID, len(x), 80, mode, 8, target_res=48) == held + frame.nbytes
    assert estimate_bytes(N_GRID, len(x), 80, mode, 8) < held  # without the target grid's fields


def test_frames_are_numbered_without_gaps(tmp_path):
    img = np.full((8, 8, 3), 7, np.uint8)
    w = FrameWriter(tmp_path)
    for k in range(12):
        w.write(img + k)
    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert names == [f"frame_{k:05d}.png" for k in range(12)]
    assert np.asarray(Image.open(tmp_path / "frames" / "frame_00011.png"))[0, 0, 0] == 18
    w = FrameWriter(tmp_path, clear=False)  # extending an animation continues the numbering
    w.write(img)
    assert [p.name for p in frame_paths(w.frames_dir)][-2:] == ["frame_00011.png", "frame_00012.png"]
    w = FrameWriter(tmp_path)  # a new run starts over
    w.write(img)
    assert [p.name for p in frame_paths(w.frames_dir)] == ["frame_00000.png"]


def test_gif_has_downscaled_size_and_every_frame(tmp_path):
    w = FrameWriter(tmp_path)
    for k in range(6):
        img = np.full((128, 96, 3), 255, np.uint8)
        img[:, : 16 * (k + 1)] = RED
        w.write(img)
    n = write_gif(w.frames_dir, tmp_path / "animation.gif", max_size=64, fps=20)
    with Image.open(tmp_path / "animation.gif") as gif:
        assert n == 6 and gif.n_frames == 6 and gif.size == (48, 64)
        assert gif.info["duration"] == 50
        gif.seek(2)
        frame = np.asarray(gif.convert("RGB"))
        assert (frame[32, 2] == RED).all() and (frame[32, -2] == WHITE).all()


def test_sheet_places_images_under_labels():
    images = [np.full((64, 64, 3), v, np.uint8) for v in (0, 60, 120, 180)]
    out = sheet(images, ["initial", "middle", "final", "target"], gap=8, label_height=20)
    assert out.shape == (84, 4 * 64 + 3 * 8, 3) and out.dtype == np.uint8
    for k, im in enumerate(images):
        np.testing.assert_array_equal(out[20:, k * 72: k * 72 + 64], im)
        label = out[:20, k * 72: k * 72 + 64]
        assert (label < 128).any() and (label == 255).mean() > 0.5  # dark text on white
    with pytest.raises(ValueError):
        sheet(images, ["one label"])


def test_loss_plot_draws_a_decreasing_log_curve(tmp_path):
    losses = 10.0 ** -np.linspace(0, 3, 40)
    path = loss_plot(np.append(losses, np.nan), tmp_path / "loss.png")
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert img.shape == (400, 640, 3)
    curve = (img[..., 0] > 150) & (img[..., 1] < 80) & (img[..., 2] < 80)
    rows, cols = np.nonzero(curve)
    left = rows[cols < cols.min() + 5].mean()
    right = rows[cols > cols.max() - 5].mean()
    assert right - left > 250  # three decades fall most of the plot's height
    mid = rows[np.abs(cols - (cols.min() + cols.max()) / 2) < 3].mean()
    assert abs(mid - (left + right) / 2) < 15  # a straight line on a log axis
    assert (img[:, :60] < 100).any()  # tick labels left of the axis
