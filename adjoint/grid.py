"""Reverse grid operations (eq 49-53, plus gravity, walls and the empty-node threshold)."""
import taichi as ti

from mls_mpm.grid import wall_mask


@ti.func
def grid_op_reverse_node(s: ti.template(), a: ti.template(), f, i, j):
    """dL/dp_i = M g / m_i (eq 50), dL/dm_i = -(p_i / m_i) . M g / m_i (eq 52-53), M the wall mask.

    Gravity adds a constant, so it passes g through unchanged; empty nodes (m_i <= m_eps, zero
    velocity in the forward pass) pass nothing back, the same threshold as the forward pass.
    """
    m = s.grid_m[f, i, j]
    g_p = ti.Vector.zero(float, 2)
    g_m = 0.0 * m
    if m > s.m_eps:
        v_free = s.grid_p[f, i, j] / m
        g_v = a.adj_grid_v[i, j] * wall_mask(s, ti.Vector([i, j]), v_free + s.dt * ti.Vector(s.gravity))
        g_p = g_v / m
        g_m = -v_free.dot(g_v) / m
    a.adj_grid_p[i, j] = g_p
    a.adj_grid_m[i, j] = g_m


@ti.kernel
def grid_op_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse grid operations of step f (twin of mls_mpm.grid.grid_op)."""
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_reverse_node(s, a, f, i, j)
