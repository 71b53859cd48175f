"""Outlines: contours of a pixel field by marching squares on the pixel samples, drawn antialiased.

The body's outline is the contour of m(x) / rest_node_mass at the colormap's "empty" level, the target's the
contour of its sampled mass grid at `target_level`. `cell_segments` traces the contour in one cell of four pixel
samples (endpoints interpolated linearly along the cell's edges, saddles resolved by the cell-center average);
`draw_outline` draws it over an image field in one launch; `contour` returns the segments themselves.
Segment endpoints are continuous pixel coordinates (column, row): pixel (r, c) spans [c, c + 1) x [r, r + 1),
its sample at the center.
"""
import numpy as np
import taichi as ti

from .colormap import put, to_u8
from .sampling import clear, real_dtype


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
    real = real_dtype()
    count = np.zeros((rows - 1, cols - 1), np.int32)
    ends = np.zeros((rows - 1, cols - 1, 2, 2, 2), real)
    contour_cells(field, level, count, ends)
    keep = np.arange(2) < count[..., None]  # [r, c, k]: segment k of cell (r, c) exists
    return ends[keep].astype(np.float64)
