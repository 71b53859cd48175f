"""Grid operations of one step: eq 17, gravity, walls and the guarded division at empty nodes."""
import taichi as ti


@ti.func
def wall_mask(s: ti.template(), I, v):
    """1 where a velocity component survives the walls, 0 where it is zeroed.

    Nodes closer than `bound` cells to an edge (index < bound or > n_grid - 1 - bound):
    slip zeroes the component moving into the wall, sticky the whole velocity.
    """
    mask = ti.Vector([1.0, 1.0])
    for d in ti.static(range(2)):
        near_low = I[d] < s.bound
        near_high = I[d] > s.n_grid - 1 - s.bound
        if ti.static(s.sticky):
            if near_low or near_high:
                mask = ti.Vector([0.0, 0.0])
        else:
            if (near_low and v[d] < 0) or (near_high and v[d] > 0):
                mask[d] = 0.0
    return mask


@ti.func
def free_velocity(s: ti.template(), f, i, j):
    """(p_i + m_i dt g) / (m_i + m_eps): eq 17 with gravity's impulse, before the walls.

    m_eps = 1e-20 m_p (f32: 1e-12 m_p) guards the division at empty nodes (v = 0 there) without a cut or a kink:
    p_i and m_i both carry the weights N_ip, so the quotient stays bounded and smooth as m_i -> 0, and at any
    node mass that matters (m_i >= 1e-4 m_p) m_eps changes it by less than round-off.
    """
    m = s.grid_m[f, i, j]
    return (s.grid_p[f, i, j] + m * s.dt * ti.Vector(s.gravity)) / (m + s.m_eps)


@ti.func
def grid_op_node(s: ti.template(), f, i, j):
    """v_i = p_i / m_i (eq 17) + dt g, then walls (free_velocity: the guarded division)."""
    v = free_velocity(s, f, i, j)
    s.grid_v[f, i, j] = v * wall_mask(s, ti.Vector([i, j]), v)


@ti.kernel
def grid_op(s: ti.template(), f: ti.i32):
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_node(s, f, i, j)
