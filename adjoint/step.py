"""Reverse time stepping (twin of mls_mpm.step): the forward's loops in reverse order, in the same two schedules.

Each reverse step consumes the adjoints of step f + 1 and zeroes them after use (particle slot (f+1) % 2 and
the grid velocity adjoint), so the next reverse step finds its accumulators zero without an extra loop.
"""
import taichi as ti

from .grid import grid_op_reverse_node
from .state import zero_particle
from .transfer import g2p_reverse_particle, p2g_reverse_particle


@ti.func
def grid_node_reverse_and_clear(s: ti.template(), a: ti.template(), f, i, j):
    if ti.static(s.lanes > 0):  # dL/dv_i = the sum of the threads' private grids, zeroed for the next step
        g = ti.Vector.zero(float, 2)
        for lane in ti.static(range(s.lanes)):
            g += a.lane_adj_v[lane, i, j]
            a.lane_adj_v[lane, i, j] = ti.Vector.zero(float, 2)
        a.adj_grid_v[i, j] = g
    grid_op_reverse_node(s, a, f, i, j)
    a.adj_grid_v[i, j] = ti.Vector.zero(float, 2)


@ti.func
def p2g_reverse_and_clear(s: ti.template(), a: ti.template(), f, p):
    p2g_reverse_particle(s, a, f, p)
    zero_particle(a, (f + 1) % 2, p)
    slot = f % 2
    total = a.adj_x[slot, p].sum() + a.adj_v[slot, p].sum() + a.adj_C[slot, p].sum() + a.adj_F[slot, p].sum()
    if ti.math.isnan(total) or ti.math.isinf(total):  # NaN or Inf in step f's adjoint of particle p: keep the latest step (first seen)
        code = ti.cast(f, ti.i64) * s.n_particles + p
        if a.fault[None] < code:
            a.fault[None] = code


@ti.func
def step_reverse_loops(s: ti.template(), a: ti.template(), f):
    """Reverse G2P, reverse grid operations, reverse P2G of step f (reverse G2P scatters like forward P2G)."""
    if ti.static(s.lanes > 0):
        ti.loop_config(block_dim=1)
        for lane in range(s.lanes):
            for p in range(lane * s.lane_chunk, ti.min((lane + 1) * s.lane_chunk, s.n_particles)):
                g2p_reverse_particle(s, a, f, p, lane)
    else:
        for p in range(s.n_particles):
            g2p_reverse_particle(s, a, f, p, 0)
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_node_reverse_and_clear(s, a, f, i, j)
    for p in range(s.n_particles):
        p2g_reverse_and_clear(s, a, f, p)


@ti.kernel
def substep_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse step f in one launch of parallel loops (twin of mls_mpm.step.substep)."""
    step_reverse_loops(s, a, f)


@ti.kernel
def run_reverse_serial(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 in one launch, serially (twin of run_serial; s.lanes must be 0)."""
    ti.loop_config(serialize=True)
    for k in range(f1 - f0):
        step_reverse_loops(s, a, f1 - 1 - k)
