"""Reverse grid operations (eq 49-53, plus gravity, walls and the guarded division at empty nodes)."""
import taichi as ti

from mls_mpm.grid import free_velocity, wall_mask
from mls_mpm.state import pack_mp, unpack_mp


@ti.func
def grid_op_node_reverse(s: ti.template(), a: ti.template(), f, I):
    """dL/dp_i = M dL/dv_i / m_i (eq 50), dL/dm_i = -(p_i / m_i) . M dL/dv_i / m_i (eq 52-53), M the wall mask,
    stored together as (dL/dp_i, dL/dm_i) in a.adj_grid_mp.

    With gravity's impulse and the guard, v = (p + m dt g) / (m + m_eps): dL/dp_i = M dL/dv_i / (m_i + m_eps)
    and dL/dm_i = (dt g - v_free) . dL/dp_i, which is eq 52-53 up to m_eps (v_free - dt g = p_i / m_i).
    """
    v_free = free_velocity(s, f, I)
    _, m = unpack_mp(s.grid_mp[f, I])
    adj_p = a.adj_grid_v[I] * wall_mask(s, I, v_free) / (m + s.m_eps)
    adj_m = (s.dt * ti.Vector(s.gravity) - v_free).dot(adj_p)
    a.adj_grid_mp[I] = pack_mp(adj_p, adj_m)


@ti.kernel
def grid_op_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse grid operations of step f (twin of mls_mpm.grid.grid_op)."""
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        grid_op_node_reverse(s, a, f, I)
