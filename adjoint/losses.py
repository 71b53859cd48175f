"""Back-propagation initialization (eq 41-46): the loss seeds on the final step's particles, twins of mls_mpm.losses."""
import taichi as ti

from mls_mpm.config import STENCIL
from mls_mpm.kernels import axis0_column, join, on_grid, roll, slab_dN, slab_dN_add, slab_offsets, stencil, weights
from mls_mpm.losses import OT_KINDS, node_penalty, node_residual, splat_value
from mls_mpm.sizes import n_live

from .state import add_own, zero_step


@ti.kernel
def grid_loss_reverse(s: ti.template(), g: ti.template()):
    """dL/dm_i = w_g alpha_i (m_i - m_iu) (eq 41, 72); log loss: w_g alpha_i r_i / (m_i + 1)."""
    for I in ti.grouped(g.m):
        r = node_penalty(g, I) * node_residual(g, I)
        if ti.static(g.kind == "log_mass"):
            r /= g.m[I] + 1.0  # m_i >= 0, so no division by zero
        g.adj_m[I] = r


@ti.kernel
def ot_loss_reverse(s: ti.template(), g: ti.template()):
    """dL/dm_i = w_g dS/dm_i, the Sinkhorn potentials' gradient that ot_loss left in g.seed."""
    for I in ti.grouped(g.m):
        g.adj_m[I] = g.seed[I]


@ti.kernel
def splat_reverse(s: ti.template(), g: ti.template(), a: ti.template(), f: ti.i32):
    """dL/dx_p += sum_i dN/dx_p (value_p . dL/dm_i) with g's dx (eq 42-43)."""
    for p in range(n_live(s)):
        base, fx = stencil(s.x[f, p], g.inv_dx)
        w, dw = weights(fx)
        value = splat_value(s, g, p)
        adj_x = ti.Vector.zero(float, s.dim)
        w0, dw0 = axis0_column(w), axis0_column(dw)
        for i0 in range(STENCIL):  # the stencil's outer loop, a runtime loop: see mls_mpm.kernels
            adj_x = splat_slab_gather(g, base, w0[0], dw0[0], w, dw, value, i0, adj_x)
            w0, dw0 = roll(w0), roll(dw0)
        add_own(a.adj_x, f % 2, p, adj_x)  # particle p's own entry: state.add_own, not an atomic add


@ti.func
def splat_slab_gather(g: ti.template(), base, w0, dw0, w, dw, value, i0, adj_x):
    """Slab i0 of splat_reverse (w0, dw0: its axis-0 weights w[i0, 0], dw[i0, 0]): sum over its nodes on the loss
    grid of dN/dx_p (value_p . dL/dm_i), added to adj_x (kernels.slab_dN_add: the slab's axis-0 factor taken out; a
    node off the grid adds nothing)."""
    acc = ti.Vector.zero(float, base.n)
    for o2 in ti.static(slab_offsets(base.n)):
        I = base + join(i0, o2)
        c = 0.0
        if on_grid(I, g.m):
            c = value.dot(g.adj_m[I])
        acc = slab_dN_add(acc, w, dw, o2, c)
    return adj_x + slab_dN(acc, w0, dw0, g.inv_dx)


@ti.kernel
def position_loss_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """dL/dx_p += x_p - x_pu (eq 10)."""
    for p in range(n_live(s)):
        add_own(a.adj_x, f % 2, p, s.x[f, p] - s.target_x[p])


def evaluate_reverse(s, a, f):
    """Seed the reverse pass (twin of mls_mpm.losses.evaluate): set dL/d(x, v, C, F) of step f from the loss
    (v, C, F get zero: eq 44-46)."""
    zero_step(s, a, f)
    for g in s.active_grids:
        if g.kind in OT_KINDS:
            ot_loss_reverse(s, g)
        else:
            grid_loss_reverse(s, g)
        splat_reverse(s, g, a, f)
    if s.has_position_loss:
        position_loss_reverse(s, a, f)
