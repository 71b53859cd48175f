"""Particles onto a grid, and a grid onto pixel fields: m(x) = sum_i N(x - x_i) m_i, the "fragment shader" of
thesis 7.1, with the simulation's own cubic B-spline basis (`kernels.stencil`, `kernels.weights`).

`splat_particle` is the P2G of one particle's value (eq 12, 15) that the loss grids share. N(x) = N1(x0/dx)
N1(x1/dx) is separable, so a grid is sampled at the pixel centers in two passes: along x once per pixel column
onto every grid line (`sample_columns`), then along y per pixel (`sample_pixel`), 4 + 4 multiply-adds instead
of 16 per pixel. Pixels whose stencils reach no node with mass are exactly 0 and skip the sampling (`live_box`).

Pixel fields are indexed [row, column]; the y axis points up like the domain's, so row 0 is y = 1 and column 0
is x = 0. Pixel (r, c) samples the domain point ((c + 1/2) / size, 1 - (r + 1/2) / size).
"""
import numpy as np
import taichi as ti
from taichi.lang import impl

from .kernels import STENCIL, splat_particle, stencil, weights


def real_dtype():
    """The numpy float type of Taichi's default float (the arrays handed to the kernels)."""
    return np.float64 if impl.current_cfg().default_fp == ti.f64 else np.float32


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
def splat_mass(grid_m: ti.template(), inv_dx, x: ti.types.ndarray(), m: ti.types.ndarray(), n):
    """m_i = sum_p N(x_i - x_p) m_p (eq 15) on a cleared grid. The splat runs on one thread: thousands of
    particles take less time so than with float atomics, and the sums run in particle order, so a frame's bytes
    are reproducible."""
    clear(grid_m)
    ti.loop_config(serialize=True)
    for p in range(n):
        splat_particle(grid_m, ti.Vector([x[p, 0], x[p, 1]]), inv_dx, m[p])


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
def upload_grid(grid: ti.template(), values: ti.types.ndarray()):
    for i, j in grid:
        grid[i, j] = values[i, j]
