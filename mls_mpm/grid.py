"""Grid operations of one step: eq 17, gravity, walls and the empty-node threshold."""
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
def grid_op_node(s: ti.template(), f, i, j):
    """v_i = p_i / m_i (eq 17) + dt g, then walls; empty nodes (m_i <= m_eps) get zero velocity."""
    m = s.grid_m[f, i, j]
    v = ti.Vector.zero(float, 2)
    if m > s.m_eps:
        v = s.grid_p[f, i, j] / m + s.dt * ti.Vector(s.gravity)
        v *= wall_mask(s, ti.Vector([i, j]), v)
    s.grid_v[f, i, j] = v


@ti.kernel
def grid_op(s: ti.template(), f: ti.i32):
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_node(s, f, i, j)
