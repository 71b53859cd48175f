"""Cubic B-spline weights and the 4^dim stencil (eq 1-2: N(x) = prod_d N1(x_d / dx)), for dim = 2 and 3."""
import taichi as ti

from .config import STENCIL


def offsets(dim):
    """The 4^dim node offsets of the stencil, first axis outermost (as ti.ndrange(4, 4)); loop over them with
    `for o in ti.static(offsets(dim))` so that the loop unrolls at compile time."""
    return ti.grouped(ti.ndrange(*[STENCIL] * dim))



@ti.func
def stencil(x, inv_dx):
    """base = floor(x/dx) - 1 and the fractional offset fx = x/dx - base, in [1, 2) per axis."""
    base = ti.cast(ti.floor(x * inv_dx), ti.i32) - 1
    fx = x * inv_dx - ti.cast(base, float)
    return base, fx


@ti.func
def weights(fx):
    """Rows j = 0..3, one column per axis: N1(t) and dN1/dt with t = fx - j.

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
def node_N(w, offset):
    """N(x_i - x_p) = prod_d N1 for node base + offset (eq 1)."""
    N = w[offset[0], 0]
    for d in ti.static(range(1, offset.n)):
        N *= w[offset[d], d]
    return N


@ti.func
def node_weight(w, dw, offset, inv_dx):
    """N(x_i - x_p) for node base + offset, and its gradient with respect to x_p (eq 2)."""
    dim = ti.static(offset.n)
    dN = ti.Vector.zero(float, dim)
    for e in ti.static(range(dim)):
        g = dw[offset[0], 0] if ti.static(e == 0) else w[offset[0], 0]
        for d in ti.static(range(1, dim)):
            g *= dw[offset[d], d] if ti.static(d == e) else w[offset[d], d]
        dN[e] = g
    return node_N(w, offset), dN * inv_dx


@ti.func
def inside(base, n) -> ti.i32:
    """Whether the whole 4^dim stencil from base lies on the grid of n nodes per axis."""
    ok = 1
    for d in ti.static(range(base.n)):
        ok = ok and base[d] >= 0 and base[d] <= n - STENCIL
    return ok


@ti.func
def on_grid(I, grid: ti.template()) -> ti.i32:
    """Whether node I lies on the field `grid` (a loss grid's nodes beyond the domain are dropped)."""
    ok = 1
    for d in ti.static(range(I.n)):
        ok = ok and 0 <= I[d] < grid.shape[d]
    return ok


@ti.func
def splat_particle(grid: ti.template(), X, inv_dx, value):
    """P2G of one particle's value (m_p, eq 15, or m_p c_p, eq 12) onto the 4^dim nodes around X:
    grid[i] += N(x_i - X) value, nodes off the grid dropped (a loss grid's nodes beyond the domain)."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    for o in ti.static(offsets(X.n)):
        I = base + o
        if on_grid(I, grid):
            grid[I] += node_N(w, o) * value
