"""Offline renderers: MPM mass rendering (thesis 7.1), grid color fields (7.5, Figs 7-8), particles (Fig 3).

A `Renderer` is built once per run; it owns its fields and renders one frame at a time from numpy arrays.
Pixels sample the fields with the simulation's own cubic B-spline basis (`kernels.stencil`, `kernels.weights`):
m(x) = sum_i N(x - x_i) m_i, the "fragment shader" of thesis 7.1. N(x) = N1(x0/dx) N1(x1/dx) is separable, so
the sum runs in two passes: along x once per pixel column onto every grid line (`sample_columns`), then along y
per pixel (`sample_pixel`), 4 + 4 multiply-adds instead of 16 per pixel. A mass or color frame is one kernel
launch (P2G, both passes and the shading) painting the Renderer's white image field, copied out as the frame; pixels
whose stencils reach no node with mass are exactly 0 and skip the sampling (`live_box`).

Outlines (the body's at the "empty" threshold, the target's at `target_level`) are contours of a pixel field,
traced by marching squares on the pixel samples and drawn antialiased (`draw_outline`, one launch each).

Images are uint8 (size, size, 3) arrays indexed [row, column]; the y axis points up like the domain's, so
row 0 is y = 1 and column 0 is x = 0. Pixel (r, c) samples the domain point ((c + 1/2) / size, 1 - (r + 1/2) / size).
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti
from taichi.lang import impl

from .kernels import STENCIL, stencil, weights

MODES = ("mass", "color", "particles")

# The mass colormap's path, in order: zero (or nearly zero) mass, low, medium, high (thesis 7.1).
WHITE = (1.0, 1.0, 1.0)
BLUE = (0.0, 0.0, 1.0)
GREEN = (0.0, 1.0, 0.0)
RED = (1.0, 0.0, 0.0)
PATH = (WHITE, BLUE, GREEN, RED)

BODY_COLOR = (0.85, 0.1, 0.1)  # particles of the body (Fig 3: red)
TARGET_COLOR = (0.0, 0.6, 0.0)  # target positions (Fig 3: green)
TARGET_OUTLINE_COLOR = (0.0, 0.0, 0.0)  # contour of the target mass grid
BODY_OUTLINE_COLOR = (0.35, 0.35, 0.35)  # contour of the body at the "empty" threshold


@dataclass(frozen=True)
class Thresholds:
    """Levels of normalised mass t = m(x) / rest_node_mass at which the mass colormap reaches each color.

    t <= empty: white; empty..low: white -> blue; low..mid: blue -> green; mid..high: green -> red;
    t >= high: red (clamped). Material at rest density has t = 1 and renders red. The color mode blends
    c(x) / m(x) from white over the same empty..low band, and the body outline is the contour t = empty.
    """

    empty: float = 0.02
    low: float = 0.25
    mid: float = 0.6
    high: float = 1.0

    def __post_init__(self):
        levels = (self.empty, self.low, self.mid, self.high)
        if not (all(np.isfinite(levels)) and 0.0 <= self.empty < self.low < self.mid < self.high):
            raise ValueError(f"thresholds = {levels}: expected 0 <= empty < low < mid < high")

    def as_tuple(self):
        return (self.empty, self.low, self.mid, self.high)


def path_position(t, thresholds: Thresholds = Thresholds()):
    """Position s in [0, 3] along white -> blue -> green -> red of normalised masses t (numpy reference).

    Non-decreasing in t; the color of t is PATH[floor(s)] blended linearly towards the next color by frac(s).
    """
    levels = np.asarray(thresholds.as_tuple())
    return np.interp(np.asarray(t, dtype=np.float64), levels, np.arange(4.0))


def path_color(s):
    """RGB floats (..., 3) of path positions s in [0, 3] (numpy reference of the `palette` ti.func)."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 3.0)
    return np.stack([np.interp(s, np.arange(4.0), [c[k] for c in PATH]) for k in range(3)], axis=-1)


@ti.func
def pixel_center(r, c, size):
    """The domain point sampled by pixel (row r, column c); rows count down from y = 1."""
    return ti.Vector([(ti.cast(c, float) + 0.5) / size, 1.0 - (ti.cast(r, float) + 0.5) / size])


@ti.func
def axis_stencil(X, inv_dx, axis, n):
    """The 4 nodes around X along one axis and their 1D weights N1 (eq 2), for a grid of n nodes per axis.

    Nodes off the grid get weight 0 and an index clamped onto it, so that a sum over the 4 drops them
    without a branch (grid values are finite, so 0 * g_i adds exactly 0).
    """
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    I = ti.Vector([0] * STENCIL)
    W = ti.Vector([0.0] * STENCIL, dt=float)
    for k in ti.static(range(STENCIL)):
        i = base[axis] + k
        I[k] = ti.min(ti.max(i, 0), n - 1)
        W[k] = ti.select(0 <= i < n, w[k, axis], 0.0)
    return I, W


@ti.func
def clear(grid: ti.template()):
    """Zero a scalar or vector field (a parallel loop of the calling kernel)."""
    for I in ti.grouped(grid):
        grid[I] = ti.zero(grid[I])


@ti.func
def scatter(grid: ti.template(), X, inv_dx, value):
    """P2G of one particle's value onto the 4x4 nodes around X (eq 15), nodes off the grid dropped."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    for i, j in ti.static(ti.ndrange(STENCIL, STENCIL)):
        I = base + ti.Vector([i, j])
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1]:
            grid[I] += w[i, 0] * w[j, 1] * value


@ti.func
def sample_columns(grid: ti.template(), line: ti.template(), inv_dx):
    """First pass of the separable interpolation m(x) = sum_i N1(x0/dx - i0) N1(x1/dx - i1) m_i (eq 1-2):
    line[j, c] = sum_i0 N1(x0/dx - i0) g[i0, j], the field along grid line y = j dx at pixel column c's x."""
    size = line.shape[1]
    for c in range(size):
        I, W = axis_stencil(pixel_center(0, c, size), inv_dx, 0, grid.shape[0])
        for j in range(grid.shape[1]):
            acc = W[0] * grid[I[0], j]
            for k in ti.static(range(1, STENCIL)):
                acc += W[k] * grid[I[k], j]
            line[j, c] = acc


@ti.func
def row_stencil(r, line: ti.template(), inv_dx):
    """The 4 grid lines J around pixel row r and their weights W (`axis_stencil` along y)."""
    return axis_stencil(pixel_center(r, 0, line.shape[1]), inv_dx, 1, line.shape[0])


@ti.func
def sample_pixel(line: ti.template(), c, J, W):
    """Second pass: sum_j N1(x1/dx - j) line[j, c] over the 4 grid lines J around the pixel's row."""
    acc = W[0] * line[J[0], c]
    for k in ti.static(range(1, STENCIL)):
        acc += W[k] * line[J[k], c]
    return acc


@ti.func
def sample_rows(line: ti.template(), inv_dx, scale, out: ti.template()):
    """out[r, c] = scale * sum_j N1(x1/dx - j) line[j, c] at every pixel: the second pass for all rows."""
    for r in range(out.shape[0]):
        J, W = row_stencil(r, line, inv_dx)
        for c in range(out.shape[1]):
            out[r, c] = scale * sample_pixel(line, c, J, W)


@ti.func
def live_box(grid: ti.template(), box: ti.template(), inv_dx, size):
    """box = (first row, last row, first column, last column) of the pixels whose stencils reach a node of
    grid holding mass (first > last: none). Elsewhere m(x) is a sum of zero terms, exactly 0, so the frame
    kernels write 0 there without sampling. One thread: a scan of the grid and 2 x size 1D stencils."""
    for _ in range(1):
        lo = ti.Vector([grid.shape[0], grid.shape[1]])  # bounding box of the nodes holding mass
        hi = ti.Vector([-1, -1])
        for i, j in ti.ndrange(grid.shape[0], grid.shape[1]):
            if grid[i, j] != 0.0:
                lo = ti.min(lo, ti.Vector([i, j]))
                hi = ti.max(hi, ti.Vector([i, j]))
        first = ti.Vector([size, size])  # [column, row] ranges; rows are monotone in y like columns in x
        last = ti.Vector([-1, -1])
        for p in range(size):
            X = pixel_center(p, p, size)  # the x of column p and the y of row p
            for a in ti.static(range(2)):
                I, W = axis_stencil(X, inv_dx, a, grid.shape[a])
                reach = 0
                for k in ti.static(range(STENCIL)):
                    reach |= W[k] > 0.0 and lo[a] <= I[k] <= hi[a]
                if reach:
                    first[a] = ti.min(first[a], p)
                    last[a] = ti.max(last[a], p)
        box[0], box[1], box[2], box[3] = first[1], last[1], first[0], last[0]


@ti.func
def position_on_path(t, e, low, mid, high):
    """Ti.func twin of `path_position`: piecewise linear, clamped to [0, 3].

    t >= high shares the green..red piece, clamped to s = 3 (the same value as a separate branch), so that
    masses fluctuating around `high` inside a body at rest do not flip a branch from pixel to pixel.
    """
    s = 0.0
    if t >= mid:
        s = 2.0 + ti.min((t - mid) / (high - mid), 1.0)
    elif t >= low:
        s = 1.0 + (t - low) / (mid - low)
    elif t > e:
        s = (t - e) / (low - e)
    return s


@ti.func
def palette(s):
    """Ti.func twin of `path_color`: white, blue, green, red at s = 0, 1, 2, 3, linear in between (s <= 3)."""
    white = ti.Vector(WHITE, dt=float)
    blue = ti.Vector(BLUE, dt=float)
    green = ti.Vector(GREEN, dt=float)
    red = ti.Vector(RED, dt=float)
    color = green + (red - green) * (s - 2.0)  # red at s = 3
    if s < 1.0:
        color = white + (blue - white) * s
    elif s < 2.0:
        color = blue + (green - blue) * (s - 1.0)
    return color


@ti.func
def to_u8(color):
    """RGB floats in [0, 1] to bytes, rounded."""
    return ti.cast(ti.math.clamp(color, 0.0, 1.0) * 255.0 + 0.5, ti.u8)


@ti.func
def put(image: ti.template(), r, c, rgb):
    """Write the bytes rgb to pixel (r, c) of the image field (3 x uint8 per pixel, [row, column])."""
    image[r, c] = rgb


@ti.func
def splat_mass(grid_m: ti.template(), inv_dx, x: ti.types.ndarray(), m: ti.types.ndarray(), n):
    """m_i = sum_p N(x_i - x_p) m_p (eq 15) on a cleared grid. The splat runs on one thread: thousands of
    particles take less time so than with float atomics, and the sums run in particle order, so a frame's bytes
    are reproducible."""
    clear(grid_m)
    ti.loop_config(serialize=True)
    for p in range(n):
        scatter(grid_m, ti.Vector([x[p, 0], x[p, 1]]), inv_dx, m[p])


@ti.func
def sample_live(line: ti.template(), box: ti.template(), inv_dx, scale, out: ti.template()):
    """out[r, c] = scale * m(x) at the pixels of the live box (`sample_rows` there), exactly 0 elsewhere."""
    for r in range(out.shape[0]):
        J, W = row_stencil(r, line, inv_dx)
        row_live, c0, c1 = box[0] <= r <= box[1], box[2], box[3]
        for c in range(out.shape[1]):
            t = 0.0
            if row_live and c0 <= c <= c1:
                t = scale * sample_pixel(line, c, J, W)
            out[r, c] = t


@ti.func
def paint_mass(pixel_m: ti.template(), image: ti.template(), e, low, mid, high):
    """Thesis 7.1's colormap (high mass red, medium green, low blue) painted over a white image where
    pixel_m > empty (below, position_on_path is 0: white, as the image starts)."""
    for r, c in pixel_m:
        t = pixel_m[r, c]
        if t > e:
            put(image, r, c, to_u8(palette(position_on_path(t, e, low, mid, high))))


@ti.kernel
def render_mass(grid_m: ti.template(), line_m: ti.template(), box: ti.template(), pixel_m: ti.template(),
                image: ti.template(), inv_dx: float, scale: float, x: ti.types.ndarray(), m: ti.types.ndarray(),
                n: ti.i32, e: float, low: float, mid: float, high: float):
    """Thesis 7.1 in one launch: P2G, pixel_m = scale * m(x) sampled in two separable passes, and the
    colormap painted over a white image."""
    splat_mass(grid_m, inv_dx, x, m, n)
    sample_columns(grid_m, line_m, inv_dx)
    live_box(grid_m, box, inv_dx, pixel_m.shape[0])
    sample_live(line_m, box, inv_dx, scale, pixel_m)
    paint_mass(pixel_m, image, e, low, mid, high)


@ti.kernel
def render_color(grid_m: ti.template(), grid_c: ti.template(), line_m: ti.template(), line_c: ti.template(),
                 box: ti.template(), pixel_m: ti.template(), image: ti.template(), inv_dx: float, scale: float,
                 x: ti.types.ndarray(), m: ti.types.ndarray(), colors: ti.types.ndarray(), n: ti.i32, e: float,
                 low: float):
    """Thesis 7.5 in one launch: P2G of m_i and the color-mass c_i = sum_p N(x_i - x_p) m_p c_p (eq 12),
    both sampled in two separable passes, and c(x) / m(x) faded to white as the normalised mass
    pixel_m = scale * m(x) falls from `low` to `empty`, painted over a white image."""
    clear(grid_m)
    clear(grid_c)
    ti.loop_config(serialize=True)  # as in splat_mass
    for p in range(n):
        X = ti.Vector([x[p, 0], x[p, 1]])
        scatter(grid_m, X, inv_dx, m[p])
        scatter(grid_c, X, inv_dx, m[p] * ti.Vector([colors[p, 0], colors[p, 1], colors[p, 2]]))
    sample_columns(grid_m, line_m, inv_dx)
    sample_columns(grid_c, line_c, inv_dx)
    live_box(grid_m, box, inv_dx, pixel_m.shape[0])  # c_i = 0 where m_i = 0
    sample_live(line_m, box, inv_dx, scale, pixel_m)
    for r in range(box[0], box[1] + 1):  # elsewhere pixel_m = 0: white, as the image starts
        J, W = row_stencil(r, line_c, inv_dx)
        for c in range(box[2], box[3] + 1):
            t = pixel_m[r, c]
            if t > e:  # white below
                rgb = ti.math.clamp(sample_pixel(line_c, c, J, W) / (t / scale), 0.0, 1.0)  # m(x) > e * rest > 0
                color = rgb  # the blend below at a = 1
                if t < low:
                    a = (t - e) / (low - e)
                    color = ti.Vector([1.0, 1.0, 1.0]) * (1.0 - a) + rgb * a
                put(image, r, c, to_u8(color))


@ti.kernel
def mass_field(grid_m: ti.template(), line_m: ti.template(), pixel_m: ti.template(), inv_dx: float, scale: float,
               x: ti.types.ndarray(), m: ti.types.ndarray(), n: ti.i32):
    """pixel_m = scale * m(x) of the particles' P2G mass, without shading (the body outline over particles)."""
    splat_mass(grid_m, inv_dx, x, m, n)
    sample_columns(grid_m, line_m, inv_dx)
    sample_rows(line_m, inv_dx, scale, pixel_m)


@ti.kernel
def sample(grid: ti.template(), line: ti.template(), inv_dx: float, scale: float, out: ti.template()):
    """out[r, c] = scale * m(x) at every pixel center, in two separable passes through line (size, grid rows)."""
    sample_columns(grid, line, inv_dx)
    sample_rows(line, inv_dx, scale, out)


@ti.kernel
def shade_mass(pixel_m: ti.template(), image: ti.template(), e: float, low: float, mid: float, high: float):
    """Thesis 7.1's colormap of a sampled field, painted over a white image."""
    paint_mass(pixel_m, image, e, low, mid, high)


@ti.kernel
def draw_particles(image: ti.template(), x: ti.types.ndarray(), F: ti.types.ndarray(), n: ti.i32, radius: float,
                   max_extent: float, color: ti.types.vector(3, float)):
    """Paint, for each particle, the image under F of a disc of `radius` pixels around it (Fig 3's ellipses).

    With F = I this is a dot. A pixel is inside when |F^-1 d| <= radius, d its offset in y-up pixels.
    """
    size = image.shape[0]
    rgb = to_u8(color)
    for p in range(n):
        P = ti.Vector([x[p, 0] * size, (1.0 - x[p, 1]) * size])  # (column, row) in continuous pixels
        A = ti.Matrix([[F[p, 0, 0], F[p, 0, 1]], [F[p, 1, 0], F[p, 1, 1]]])
        det = A.determinant()
        if ti.abs(det) < 1e-8:  # a (nearly) singular F has no usable inverse: draw the plain dot
            A = ti.Matrix.identity(float, 2)
            det = 1.0
        A_inv = ti.Matrix([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]]) / det
        hx = ti.min(radius * ti.sqrt(A[0, 0] ** 2 + A[0, 1] ** 2), max_extent)  # half extents of the ellipse
        hy = ti.min(radius * ti.sqrt(A[1, 0] ** 2 + A[1, 1] ** 2), max_extent)
        c0 = ti.max(ti.cast(ti.floor(P[0] - hx), ti.i32), 0)
        c1 = ti.min(ti.cast(ti.floor(P[0] + hx), ti.i32), size - 1)
        r0 = ti.max(ti.cast(ti.floor(P[1] - hy), ti.i32), 0)
        r1 = ti.min(ti.cast(ti.floor(P[1] + hy), ti.i32), size - 1)
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                d = ti.Vector([ti.cast(c, float) + 0.5 - P[0], P[1] - ti.cast(r, float) - 0.5])
                if (A_inv @ d).norm() <= radius:
                    put(image, r, c, rgb)
        rc = ti.cast(ti.floor(P), ti.i32)  # a particle thinner than a pixel still shows its own pixel
        if 0 <= rc[0] < size and 0 <= rc[1] < size:
            put(image, rc[1], rc[0], rgb)


@ti.func
def edge_crossing(P0, P1, f0, f1, level):
    """The point of the cell edge P0 -> P1 where the field, linear along the edge, equals level. On an edge
    that does not cross (f0, f1 on the same side) the result is unused; the guard only keeps it finite."""
    return P0 + (level - f0) / ti.select(f1 != f0, f1 - f0, 1.0) * (P1 - P0)


@ti.func
def cell_segments(field: ti.template(), r, c, level):
    """Marching squares in the cell whose corners are the samples at pixels (r, c), (r, c+1), (r+1, c+1),
    (r+1, c): corners k = 0..3 in that order, edge k from corner k to corner k + 1 (mod 4).

    A corner is inside when field >= level; an edge whose corners differ crosses the contour at the point
    where the field, interpolated linearly along it, equals level (`edge_crossing`). 2 crossed edges make one
    segment. 4 (the saddles: corners 0, 2 on one side, 1, 3 on the other) make two, resolved by the cell-center
    average: the segments cut off the two corners whose side differs from the center's, so a center inside
    joins the inside corners and a center below the level separates them.
    Returns (n, a0, b0, a1, b1): n = 0, 1 or 2 segments a0-b0, a1-b1, in continuous pixel coordinates
    (column, row), pixel (r, c) spanning [c, c + 1) x [r, r + 1) (its sample at the center)."""
    f = ti.Vector([field[r, c], field[r, c + 1], field[r + 1, c + 1], field[r + 1, c]])
    zero = ti.Vector([0.0, 0.0])
    n, a0, b0, a1, b1 = 0, zero, zero, zero, zero
    if f.min() < level <= f.max():  # corners on both sides (most cells lie on one side: nothing to compute)
        inside = f >= level
        crossed = 0
        for k in ti.static(range(4)):
            crossed += inside[k] != inside[(k + 1) % 4]
        u, v = ti.cast(c, float) + 0.5, ti.cast(r, float) + 0.5
        P = [ti.Vector([u, v]), ti.Vector([u + 1.0, v]), ti.Vector([u + 1.0, v + 1.0]), ti.Vector([u, v + 1.0])]
        E = [edge_crossing(P[k], P[(k + 1) % 4], f[k], f[(k + 1) % 4], level) for k in ti.static(range(4))]
        if crossed == 4:  # a saddle
            n = 2
            if inside[1] != (f.sum() / 4.0 >= level):  # corner k lies between edges k - 1 and k
                a0, b0, a1, b1 = E[0], E[1], E[2], E[3]  # cut off corners 1 and 3
            else:
                a0, b0, a1, b1 = E[3], E[0], E[1], E[2]  # cut off corners 0 and 2
        else:
            n = 1
            first = 1
            for k in ti.static(range(4)):
                if inside[k] != inside[(k + 1) % 4]:
                    if first:
                        a0 = E[k]
                        first = 0
                    else:
                        b0 = E[k]
    return n, a0, b0, a1, b1


@ti.func
def stamp_segment(ink: ti.template(), a, b, width):
    """ink = max(ink, coverage) over the pixels near segment a-b (continuous pixel coordinates):
    coverage = clamp(width / 2 + 1/2 - d, 0, 1), d the distance from the pixel's center to the segment, the
    share of the pixel a line `width` pixels wide covers where it runs straight past (antialiasing)."""
    reach = 0.5 * width + 0.5  # pixels at least this far from the segment get no ink
    lo = ti.max(ti.cast(ti.floor(ti.min(a, b) - reach), ti.i32), 0)
    hi = ti.min(ti.cast(ti.floor(ti.max(a, b) + reach), ti.i32), ti.Vector([ink.shape[1], ink.shape[0]]) - 1)
    ab = b - a
    length2 = ab.dot(ab)
    for row in range(lo[1], hi[1] + 1):
        for col in range(lo[0], hi[0] + 1):
            q = ti.Vector([ti.cast(col, float) + 0.5, ti.cast(row, float) + 0.5]) - a
            s = 0.0  # a segment of length 0 (the contour through a sample): the distance to its point
            if length2 > 0.0:
                s = ti.math.clamp(q.dot(ab) / length2, 0.0, 1.0)
            coverage = ti.min(reach - (q - s * ab).norm(), 1.0)
            if coverage > 0.0:
                ti.atomic_max(ink[row, col], coverage)


@ti.kernel
def draw_outline(field: ti.template(), ink: ti.template(), image: ti.template(), level: float, width: float,
                 color: ti.types.vector(3, float)):
    """The contour field = level, by marching squares on the pixel samples (`cell_segments`), drawn `width`
    pixels wide and antialiased over the image in one launch: each cell stamps its segments' coverage into ink
    (`stamp_segment`; a maximum, so overlapping segments do not darken their joints, and the bytes do not depend
    on the order of the cells), then each inked pixel is blended towards color by its coverage.

    The contour runs between pixel centers: none is drawn along the image border, where no cell reaches.
    """
    clear(ink)
    for r in range(field.shape[0] - 1):  # rows in parallel, the cells of a row in sequence
        for c in range(field.shape[1] - 1):
            n, a0, b0, a1, b1 = cell_segments(field, r, c, level)
            if n >= 1:
                stamp_segment(ink, a0, b0, width)
            if n == 2:
                stamp_segment(ink, a1, b1, width)
    for r, c in ink:
        alpha = ink[r, c]
        if alpha > 0.0:
            old = ti.cast(image[r, c], float) / 255.0
            put(image, r, c, to_u8(old + (color - old) * alpha))


@ti.kernel
def contour_cells(field: ti.template(), level: float, count: ti.types.ndarray(), ends: ti.types.ndarray()):
    """count[r, c] and ends[r, c, k, end, axis]: the segments of every cell of `draw_outline`'s contour."""
    for r, c in ti.ndrange(field.shape[0] - 1, field.shape[1] - 1):
        n, a0, b0, a1, b1 = cell_segments(field, r, c, level)
        count[r, c] = n
        for d in ti.static(range(2)):
            ends[r, c, 0, 0, d], ends[r, c, 0, 1, d] = a0[d], b0[d]
            ends[r, c, 1, 0, d], ends[r, c, 1, 1, d] = a1[d], b1[d]


def contour(field, level):
    """The marching-squares segments of a pixel field (a Taichi field [row, column], at least 2 x 2) at level,
    as drawn by `draw_outline`: an array (K, 2, 2) of endpoints in continuous pixel coordinates (column, row)."""
    rows, cols = field.shape
    real = np.float64 if impl.current_cfg().default_fp == ti.f64 else np.float32
    count = np.zeros((rows - 1, cols - 1), np.int32)
    ends = np.zeros((rows - 1, cols - 1, 2, 2, 2), real)
    contour_cells(field, level, count, ends)
    keep = np.arange(2) < count[..., None]  # [r, c, k]: segment k of cell (r, c) exists
    return ends[keep].astype(np.float64)


@ti.kernel
def colormap_kernel(t: ti.types.ndarray(), s: ti.types.ndarray(), rgb: ti.types.ndarray(), e: float, low: float,
                    mid: float, high: float):
    """The mass colormap on an array of normalised masses (for tests and legends)."""
    for k in range(t.shape[0]):
        s[k] = position_on_path(t[k], e, low, mid, high)
        color = to_u8(palette(s[k]))
        for d in ti.static(range(3)):
            rgb[k, d] = color[d]


@ti.kernel
def fill_white(image: ti.template()):
    for r, c in image:
        image[r, c] = ti.Vector([255, 255, 255], ti.u8)


@ti.kernel
def upload_grid(grid: ti.template(), values: ti.types.ndarray()):
    for i, j in grid:
        grid[i, j] = values[i, j]


@ti.data_oriented
class Renderer:
    """Renders frames of one run. Fields are allocated once here; `render` is called once per frame.

    n_grid: simulation grid nodes per axis (dx = 1 / n_grid); mass is splatted onto this grid.
    n_particles: the run's particle count; sizes the default per-particle buffers (other counts still work).
    size: output image side in pixels.
    rest_node_mass: mass a node holds inside material at rest density, density * dx^2; it normalises m(x).
    mode: "mass" (thesis 7.1), "color" (7.5) or "particles" (Fig 3).
    thresholds: `Thresholds` (or a 4-tuple) of the mass colormap and the color mode's fade to white.
    radius: particle dot radius in pixels ("particles" mode and target positions).
    body_outline: draw the contour m(x) / rest_node_mass = thresholds.empty over the image, the silhouette of
        the body (over particles too).
    target_level: normalised mass level of the target outline (0.5: the edge of a B-spline-smoothed shape).
    line_width: outline width in pixels.

    Outlines are marching-squares contours of the pixel-sampled field (`cell_segments`: endpoints interpolated
    linearly between pixel centers, saddles resolved by the cell-center average), drawn line_width pixels wide
    with antialiased edges (`stamp_segment`); `contour` returns the segments themselves.
    """

    def __init__(self, n_grid, n_particles, size=512, rest_node_mass=None, mode="mass", thresholds=None,
                 radius=1.5, body_outline=False, target_level=0.5, line_width=1):
        if mode not in MODES:
            raise ValueError(f"mode = {mode!r}: expected one of {', '.join(MODES)}")
        for name, value, least in (("n_grid", n_grid, STENCIL), ("n_particles", n_particles, 0),
                                   ("size", size, 1), ("line_width", line_width, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} = {value!r}: expected an integer >= {least}")
        if rest_node_mass is None or not (np.isfinite(rest_node_mass) and rest_node_mass > 0):
            raise ValueError(f"rest_node_mass = {rest_node_mass!r}: expected a number > 0 (density * dx^2)")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius = {radius!r}: expected a number of pixels > 0")
        if thresholds is None:
            thresholds = Thresholds()
        elif not isinstance(thresholds, Thresholds):
            thresholds = Thresholds(*thresholds)
        self.n_grid = int(n_grid)
        self.n_particles = int(n_particles)
        self.size = int(size)
        self.rest_node_mass = float(rest_node_mass)
        self.mode = mode
        self.thresholds = thresholds
        self.radius = float(radius)
        self.body_outline = bool(body_outline)
        self.target_level = float(target_level)
        self.line_width = int(line_width)
        self.inv_dx = float(n_grid)
        self.real = np.float64 if impl.current_cfg().default_fp == ti.f64 else np.float32

        n, s = self.n_grid, self.size
        self.grid_m = ti.field(float, shape=(n, n))  # node mass m_i (eq 15)
        self.grid_c = ti.Vector.field(3, float, shape=(n, n)) if mode == "color" else None  # color-mass c_i (eq 12)
        self.line_m = ti.field(float, shape=(n, s))  # [j, column]: m along grid line y = j dx at each column's x
        self.line_c = ti.Vector.field(3, float, shape=(n, s)) if mode == "color" else None  # the same for c
        self.box = ti.field(ti.i32, shape=4)  # pixel rows and columns reached by mass (`live_box`)
        self.pixel_m = ti.field(float, shape=(s, s))  # m(x) / rest_node_mass at each pixel center, [row, column]
        self.image = ti.Vector.field(3, ti.u8, shape=(s, s))  # the frame being drawn, RGB bytes [row, column]
        self.ink = ti.field(float, shape=(s, s))  # an outline's coverage of each pixel in [0, 1] (`draw_outline`)
        self._identity = np.tile(np.eye(2, dtype=self.real), (self.n_particles, 1, 1))  # F of plain dots
        self._target = None  # (res, grid, line, pixel field, the array uploaded), made for the first target grid

    # -- one frame ---------------------------------------------------------------------------------------
    def render(self, x, m_p, colors=None, F=None, target_x=None, target_outline=None):
        """One frame as uint8 (size, size, 3).

        x: (N, 2) positions; m_p: particle mass, a number or (N,); colors: (N, 3) RGB in [0, 1] (uint8 is
        read as 0..255), required in "color" mode; F: (N, 2, 2) deformation gradients, drawn as ellipses in
        "particles" mode (dots without); target_x: (M, 2) target positions drawn as green dots over any mode;
        target_outline: a (res, res) target mass grid whose contour at `target_level` is drawn in black.
        """
        x = self._array(x, "x", (-1, 2))
        N = len(x)
        m = self._masses(m_p, N)
        th = self.thresholds
        scale = 1.0 / self.rest_node_mass
        image = self._blank()
        if self.mode == "mass":
            render_mass(self.grid_m, self.line_m, self.box, self.pixel_m, image, self.inv_dx, scale, x, m, N,
                        *th.as_tuple())
        elif self.mode == "color":
            if colors is None:
                raise ValueError("colors: required in color mode, expected shape (N, 3)")
            colors = np.asarray(colors)
            colors = colors / 255.0 if colors.dtype == np.uint8 else colors
            colors = self._array(colors, "colors", (N, 3))
            render_color(self.grid_m, self.grid_c, self.line_m, self.line_c, self.box, self.pixel_m, image,
                         self.inv_dx, scale, x, m, colors, N, th.empty, th.low)
        else:
            if target_x is not None:
                self._dots(image, target_x, TARGET_COLOR)
                target_x = None
            if N:
                F = self._identity_for(N) if F is None else self._array(F, "F", (N, 2, 2))
                draw_particles(image, x, F, N, self.radius, self.size / 8.0, ti.Vector(BODY_COLOR))
            if self.body_outline:
                mass_field(self.grid_m, self.line_m, self.pixel_m, self.inv_dx, scale, x, m, N)
        if self.body_outline:
            self._outline(self.pixel_m, image, th.empty, BODY_OUTLINE_COLOR)
        if target_outline is not None:
            self._outline(self._target_field(target_outline), image, self.target_level, TARGET_OUTLINE_COLOR)
        if target_x is not None:
            self._dots(image, target_x, TARGET_COLOR)
        return image.to_numpy()  # each frame gets its own array

    def render_target(self, target_mass, outline=True):
        """A (res, res) target mass grid in the mass colormap (e.g. the "target" panel of a sheet).

        Entry [i, j] is the node at (i / res, j / res); it is normalised by the rest node mass of its own
        grid, rest_node_mass * (n_grid / res)^2.
        """
        field = self._target_field(target_mass)
        image = self._blank()
        shade_mass(field, image, *self.thresholds.as_tuple())
        if outline:
            self._outline(field, image, self.target_level, TARGET_OUTLINE_COLOR)
        return image.to_numpy()

    def colormap(self, t):
        """(path positions (K,), uint8 colors (K, 3)) of normalised masses t (K,) through the kernels' colormap."""
        t = np.ascontiguousarray(np.ravel(t), dtype=self.real)
        s = np.zeros_like(t)
        rgb = np.zeros((len(t), 3), dtype=np.uint8)
        if len(t):
            colormap_kernel(t, s, rgb, *self.thresholds.as_tuple())
        return s, rgb

    # -- helpers -----------------------------------------------------------------------------------------
    def _blank(self):
        """The image field, white. The frame kernels draw into this field rather than into a numpy array: on
        a GPU Taichi does not upload an array that a kernel only writes, so a white array would not stay white."""
        fill_white(self.image)
        return self.image

    def _outline(self, field, image, level, color):
        draw_outline(field, self.ink, image, level, float(self.line_width), ti.Vector(color))

    def _dots(self, image, points, color):
        points = self._array(points, "target_x", (-1, 2))
        if len(points):
            draw_particles(image, points, self._identity_for(len(points)), len(points), self.radius,
                           self.size / 8.0, ti.Vector(color))

    def _target_field(self, target):
        """The normalised, pixel-sampled field of a target mass grid; recomputed only when the grid changes."""
        target = np.asarray(target)
        if target.ndim != 2 or target.shape[0] != target.shape[1] or target.shape[0] < STENCIL:
            raise ValueError(f"target mass grid: expected shape (res, res) with res >= {STENCIL}, got {target.shape}")
        res = target.shape[0]
        if self._target is None or self._target[0] != res:
            self._target = (res, ti.field(float, shape=(res, res)), ti.field(float, shape=(res, self.size)),
                            ti.field(float, shape=(self.size, self.size)), None)
        _, grid, line, field, uploaded = self._target
        if uploaded is None or uploaded.shape != target.shape or not np.array_equal(uploaded, target):
            values = self._array(target, "target mass grid", (res, res))
            upload_grid(grid, values)
            rest = self.rest_node_mass * (self.n_grid / res) ** 2  # density * (1 / res)^2
            sample(grid, line, float(res), 1.0 / rest, field)
            self._target = (res, grid, line, field, values.copy())
        return field

    def _identity_for(self, N):
        return self._identity[:N] if N <= len(self._identity) else np.tile(np.eye(2, dtype=self.real), (N, 1, 1))

    def _masses(self, m_p, N):
        m = np.asarray(m_p, dtype=np.float64)
        if m.ndim == 0:
            m = np.full(N, float(m))
        if m.shape != (N,) or not np.all(np.isfinite(m)) or np.any(m < 0):
            raise ValueError(f"m_p: expected a number or an array of shape ({N},) of finite masses >= 0")
        return m.astype(self.real)

    def _array(self, a, name, shape):
        a = np.asarray(a, dtype=np.float64)
        want = tuple(a.shape[0] if k == -1 and a.ndim else k for k in shape)
        if a.shape != want:
            raise ValueError(f"{name}: expected shape {tuple('N' if k == -1 else k for k in shape)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: holds NaN or Inf")
        return np.ascontiguousarray(a, dtype=self.real)
