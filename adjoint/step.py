"""Reverse time stepping (twin of mls_mpm.step): the forward's loops in reverse order, in the same two schedules.

Each reverse step consumes the adjoints of step f + 1 and zeroes them after use (particle slot (f+1) % 2 and
the grid velocity adjoint), so the next reverse step finds its accumulators zero without an extra loop.
Where the forward keeps one grid velocity slot (State.every_velocity off), a reverse pass first recomputes v_i of
its last step from the stored m_i, p_i, and the reverse grid loop of step f recomputes v_i of step f - 1 for the
next reverse step's G2P (eq 17 and the walls, by the forward's own grid_op_node: one division per node).
"""
import taichi as ti

from mls_mpm.grid import grid_op, grid_op_node
from mls_mpm.state import LANE_TASK, lane_span

from .grid import grid_op_node_reverse
from .state import zero_particle
from .transfer import check_particle_reverse, g2p_particle_reverse, p2g_particle_reverse


@ti.func
def gather_lanes_reverse(s: ti.template(), a: ti.template(), I):
    """dL/dv_i = the sum of the threads' private grids, which are zeroed for the next reverse step."""
    adj_v = ti.Vector.zero(float, s.dim)
    for lane in ti.static(range(s.lanes)):
        adj_v += a.lane_adj_v[lane, I]
        a.lane_adj_v[lane, I] = ti.Vector.zero(float, s.dim)
    a.adj_grid_v[I] = adj_v


@ti.func
def grid_node_reverse(s: ti.template(), a: ti.template(), f, I, f0):
    """Reverse grid operations of node I; then dL/dv_i is zeroed for the next reverse step's scatter, and (one
    velocity slot) v_i of step f - 1 is recomputed for that step's reverse G2P when it is in the pass f0.. ."""
    if ti.static(s.lanes > 0):
        gather_lanes_reverse(s, a, I)
    grid_op_node_reverse(s, a, f, I)
    a.adj_grid_v[I] = ti.Vector.zero(float, s.dim)
    if ti.static(not s.every_velocity):
        if f - 1 >= f0:
            grid_op_node(s, f - 1, I)


@ti.func
def velocity_loop(s: ti.template(), f):
    """v_i of step f from the stored m_i, p_i (one velocity slot): the start of a reverse pass."""
    if ti.static(not s.every_velocity):
        for I in ti.grouped(ti.ndrange(*s.grid_shape)):
            grid_op_node(s, f, I)


@ti.func
def step_loops_reverse(s: ti.template(), a: ti.template(), f, f0):
    """Reverse G2P, reverse grid operations, reverse P2G and the adjoint's check of step f, in a pass down to f0.

    The forward's three loops in reverse order; reverse G2P scatters into dL/dv_i as forward P2G scatters into
    m_i, p_i, with the same private grids per thread (lanes).
    """
    if ti.static(s.lanes > 0):
        for item in range(s.lanes * LANE_TASK):  # one task per lane, one thread each: mls_mpm.state.LANE_TASK
            lane, lo, hi = lane_span(s, item)
            for p in range(lo, hi):
                g2p_particle_reverse(s, a, f, p, lane)
    else:
        for p in range(s.n_particles):
            g2p_particle_reverse(s, a, f, p, 0)
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        grid_node_reverse(s, a, f, I, f0)
    for p in range(s.n_particles):
        p2g_particle_reverse(s, a, f, p)
        zero_particle(a, (f + 1) % 2, p)
        check_particle_reverse(s, a, f, p)


@ti.kernel
def substep_reverse(s: ti.template(), a: ti.template(), f: ti.i32, f0: ti.i32):
    """Reverse step f of a pass down to f0 in one launch of parallel loops (twin of mls_mpm.step.substep)."""
    step_loops_reverse(s, a, f, f0)


def run_parallel_reverse(s, a, f0, f1):
    """Reverse steps f1-1 down to f0, one launch each (twin of mls_mpm.step.run_parallel)."""
    if not s.every_velocity:
        grid_op(s, f1 - 1)  # v_i of the pass's last step into the one slot (velocity_loop in a launch of its own)
    for f in range(f1 - 1, f0 - 1, -1):
        substep_reverse(s, a, f, f0)


@ti.kernel
def run_serial_reverse(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 in one launch, serially (twin of run_serial; s.lanes must be 0)."""
    ti.loop_config(serialize=True)
    for _ in range(1):
        velocity_loop(s, f1 - 1)
    ti.loop_config(serialize=True)
    for k in range(f1 - f0):
        step_loops_reverse(s, a, f1 - 1 - k, f0)
