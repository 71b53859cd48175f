"""Reverse grid operations (eq 49-53, plus gravity, walls and the guarded division at empty nodes)."""
import taichi as ti

from mls_mpm.grid import free_velocity, wall_mask


@ti.func
def grid_op_node_reverse(s: ti.template(), a: ti.template(), f, i, j):
    """dL/dp_i = M dL/dv_i / m_i (eq 50), dL/dm_i = -(p_i / m_i) . M dL/dv_i / m_i (eq 52-53), M the wall mask.

    With gravity's impulse and the guard, v = (p + m dt g) / (m + m_eps): dL/dp_i = M dL/dv_i / (m_i + m_eps)
    and dL/dm_i = (dt g - v_free) . dL/dp_i, which is eq 52-53 up to m_eps (v_free - dt g = p_i / m_i).
    """
    v_free = free_velocity(s, f, i, j)
    adj_p = a.adj_grid_v[i, j] * wall_mask(s, ti.Vector([i, j]), v_free) / (s.grid_m[f, i, j] + s.m_eps)
    a.adj_grid_p[i, j] = adj_p
    a.adj_grid_m[i, j] = (s.dt * ti.Vector(s.gravity) - v_free).dot(adj_p)


@ti.kernel
def grid_op_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse grid operations of step f (twin of mls_mpm.grid.grid_op)."""
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_node_reverse(s, a, f, i, j)
