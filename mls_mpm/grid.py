"""Grid operations of one step: eq 17, gravity, walls and the guarded division at empty nodes (any dim)."""
import taichi as ti

from .state import unpack_mp


@ti.func
def wall_mask(s: ti.template(), I, v):
    """1 where a velocity component survives the walls, 0 where it is zeroed.

    Nodes closer than `bound` cells to a wall (index < bound or > n_grid - 1 - bound along an axis):
    slip zeroes the component moving into the wall, sticky the whole velocity.
    """
    mask = ti.Vector.one(float, s.dim)
    for d in ti.static(range(s.dim)):
        near_low = I[d] < s.bound
        near_high = I[d] > s.n_grid - 1 - s.bound
        if ti.static(s.sticky):
            if near_low or near_high:
                mask = ti.Vector.zero(float, s.dim)
        else:
            if (near_low and v[d] < 0) or (near_high and v[d] > 0):
                mask[d] = 0.0
    return mask


@ti.func
def free_velocity(s: ti.template(), f, I):
    """(p_i + m_i dt g) / (m_i + m_eps) at node I: eq 17 with gravity's impulse, before the walls.

    m_eps = 1e-20 m_p (f32: 1e-12 m_p) guards the division at empty nodes (v = 0 there) without a cut or a kink:
    p_i and m_i both carry the weights N_ip, so the quotient stays bounded and smooth as m_i -> 0, and at any
    node mass that matters (m_i >= 1e-4 m_p) m_eps changes it by less than round-off.
    """
    p, m = unpack_mp(s.grid_mp[f, I])
    return (p + m * s.dt * ti.Vector(s.gravity)) / (m + s.m_eps)


@ti.func
def velocity_slot(s: ti.template(), f):
    """Where v_i of step f lives in s.grid_v: at f when every step keeps its own (State.every_velocity), else in
    the one slot 0."""
    slot = 0
    if ti.static(s.every_velocity):
        slot = f
    return slot


@ti.func
def grid_op_node(s: ti.template(), f, I):
    """v_i = p_i / m_i (eq 17) + dt g, then walls (free_velocity: the guarded division)."""
    v = free_velocity(s, f, I)
    s.grid_v[velocity_slot(s, f), I] = v * wall_mask(s, I, v)


@ti.kernel
def grid_op(s: ti.template(), f: ti.i32):
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        grid_op_node(s, f, I)
