"""Cubic B-spline weights and the 4x4 stencil (eq 1-2: N(x) = N1(x0/dx) N1(x1/dx))."""
import taichi as ti

from .config import STENCIL


@ti.func
def stencil(x, inv_dx):
    """base = floor(x/dx) - 1 and the fractional offset fx = x/dx - base, in [1, 2) per axis."""
    base = ti.cast(ti.floor(x * inv_dx), ti.i32) - 1
    fx = x * inv_dx - ti.cast(base, float)
    return base, fx


@ti.func
def weights(fx):
    """Rows j = 0..3: N1(t) and dN1/dt with t = fx - j per axis.

    N1(t) = |t|^3/2 - t^2 + 2/3 for |t| < 1 and (2 - |t|)^3/6 for 1 <= |t| < 2. Since fx is in [1, 2),
    row j always falls in the same piece, so the weights need no branch.
    """
    t0 = fx
    t1 = fx - 1.0
    t2 = fx - 2.0
    t3 = fx - 3.0
    w = ti.Matrix.rows([
        (2.0 - t0) ** 3 / 6.0,
        0.5 * t1 ** 3 - t1 ** 2 + 2.0 / 3.0,
        -0.5 * t2 ** 3 - t2 ** 2 + 2.0 / 3.0,
        (2.0 + t3) ** 3 / 6.0,
    ])
    dw = ti.Matrix.rows([
        -0.5 * (2.0 - t0) ** 2,
        1.5 * t1 ** 2 - 2.0 * t1,
        -1.5 * t2 ** 2 - 2.0 * t2,
        0.5 * (2.0 + t3) ** 2,
    ])
    return w, dw


@ti.func
def node_weight(w, dw, offset, inv_dx):
    """N(x_i - x_p) for node base + offset, and its gradient with respect to x_p."""
    N = w[offset[0], 0] * w[offset[1], 1]
    dN = ti.Vector([dw[offset[0], 0] * w[offset[1], 1], w[offset[0], 0] * dw[offset[1], 1]]) * inv_dx
    return N, dN


@ti.func
def inside(base, n) -> ti.i32:
    """Whether the whole 4x4 stencil from base lies on an n x n grid."""
    return base[0] >= 0 and base[1] >= 0 and base[0] <= n - STENCIL and base[1] <= n - STENCIL


@ti.func
def splat_particle(grid: ti.template(), X, inv_dx, value):
    """P2G of one particle's value (m_p, eq 15, or m_p c_p, eq 12) onto the 4x4 nodes around X:
    grid[i] += N(x_i - X) value, nodes off the grid dropped (a loss grid's nodes beyond the domain)."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    for i, j in ti.static(ti.ndrange(STENCIL, STENCIL)):
        I = base + ti.Vector([i, j])
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1]:
            grid[I] += w[i, 0] * w[j, 1] * value
