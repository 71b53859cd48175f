"""Reverse time stepping (twin of mls_mpm.step): the forward's loops in reverse order, in the same two schedules.

Each reverse step consumes the adjoints of step f + 1 and zeroes them after use (particle slot (f+1) % 2 and
the grid velocity adjoint), so the next reverse step finds its accumulators zero without an extra loop.
"""
import taichi as ti

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
def grid_node_reverse(s: ti.template(), a: ti.template(), f, I):
    """Reverse grid operations of node I; then dL/dv_i is zeroed for the next reverse step's scatter."""
    if ti.static(s.lanes > 0):
        gather_lanes_reverse(s, a, I)
    grid_op_node_reverse(s, a, f, I)
    a.adj_grid_v[I] = ti.Vector.zero(float, s.dim)


@ti.func
def step_loops_reverse(s: ti.template(), a: ti.template(), f):
    """Reverse G2P, reverse grid operations, reverse P2G and the adjoint's check of step f.

    The forward's three loops in reverse order; reverse G2P scatters into dL/dv_i as forward P2G scatters into
    m_i, p_i, with the same private grids per thread (lanes).
    """
    if ti.static(s.lanes > 0):
        ti.loop_config(block_dim=1)
        for lane in range(s.lanes):
            for p in range(lane * s.lane_chunk, ti.min((lane + 1) * s.lane_chunk, s.n_particles)):
                g2p_particle_reverse(s, a, f, p, lane)
    else:
        for p in range(s.n_particles):
            g2p_particle_reverse(s, a, f, p, 0)
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        grid_node_reverse(s, a, f, I)
    for p in range(s.n_particles):
        p2g_particle_reverse(s, a, f, p)
        zero_particle(a, (f + 1) % 2, p)
        check_particle_reverse(s, a, f, p)


@ti.kernel
def substep_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse step f in one launch of parallel loops (twin of mls_mpm.step.substep)."""
    step_loops_reverse(s, a, f)


@ti.kernel
def run_serial_reverse(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 in one launch, serially (twin of run_serial; s.lanes must be 0)."""
    ti.loop_config(serialize=True)
    for k in range(f1 - f0):
        step_loops_reverse(s, a, f1 - 1 - k)
