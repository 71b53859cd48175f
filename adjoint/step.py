"""Reverse time stepping (twin of mls_mpm.step): the forward's loops in reverse order, in the same two schedules.

A reverse pass over steps f1-1 down to f0 runs, for f = f1 down to f0, two loops: the reverse grid operations of step
f, and one particle loop that fuses the reverse P2G of step f with the reverse G2P of step f - 1 (particle_adjoint:
the particle's adjoint of step f stays in registers between them). At f = f1, the pass's start, the two loops run
only their second halves: the reverse G2P of step f1 - 1 from the adjoint of step f1 (the loss's seed). The grid
velocity adjoint is zeroed after use, so the next reverse step finds its accumulator zero without an extra loop.
Where the forward keeps one grid velocity slot (State.every_velocity off), the reverse grid loop of step f
recomputes v_i of step f - 1 from the stored m_i, p_i for the reverse G2P of step f - 1 (eq 17 and the walls, by the
forward's own grid_op_node: one division per node). With lanes the grid loop of step f visits the active boxes
(mls_mpm.active) of steps f and f - 1 that the forward stored, not the whole grid.
"""
import taichi as ti

from mls_mpm.active import node_in, reverse_box, volume
from mls_mpm.grid import grid_op_node
from mls_mpm.sizes import n_live
from mls_mpm.state import LANE_TASK, lane_span

from .grid import grid_op_node_reverse
from .state import add_own, zero_particle
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
def grid_node_reverse(s: ti.template(), a: ti.template(), f, I, f0, f1):
    """Reverse grid operations of node I at step f < f1, then dL/dv_i zeroed for the next reverse step's scatter;
    and (one velocity slot) v_i of step f - 1 recomputed for its reverse G2P when f - 1 is in the pass f0..f1-1 (at
    f = f1, the pass's start, that alone)."""
    if f < f1:
        if ti.static(s.lanes > 0):
            gather_lanes_reverse(s, a, I)
        grid_op_node_reverse(s, a, f, I)
        a.adj_grid_v[I] = ti.Vector.zero(float, s.dim)
    if ti.static(not s.every_velocity):
        if f - 1 >= f0:
            grid_op_node(s, f - 1, I)


@ti.func
def particle_adjoint(s: ti.template(), a: ti.template(), f, p, lane, f0, f1):
    """Reverse P2G of step f and reverse G2P of step f - 1 for particle p, in a pass from f1 down to f0: the reverse
    twin of the forward's G2P of step f - 1 and P2G of step f, fused per particle.

    The whole dL/d(x, v, C, F)_p^f is formed in registers: at f = f1, the pass's start, slot f1 % 2 (the loss's seed,
    or what the pass before left); below it, the G2P part of x and F that the reverse G2P of step f left in slot
    f % 2 plus the P2G part (G2P has no v^f, C^f input: their adjoints are the P2G part alone), then dL/dF_pc^k
    (eq 55, at a control step; zero for a particle off the grid, which both transfers skip) and the check. For
    f > f0 the reverse G2P of step f - 1 follows, its parts written over slot (f - 1) % 2 (the adjoint of step
    f + 1, which the previous particle loop consumed); at f = f0 the adjoint goes to slot f0 % 2 and the other slot
    is zeroed: the state a pass leaves (Simulator.grad_x0, the next pass of a chain). Each particle's adjoint is read
    and written once a step, where separate reverse G2P and P2G loops read and wrote it three times each.
    """
    dst = f % 2
    adj_x = a.adj_x[dst, p]
    adj_F = a.adj_F[dst, p]
    adj_v = ti.Vector.zero(float, s.dim)
    adj_C = ti.Matrix.zero(float, s.dim, s.dim)
    if f < f1:
        px, pv, pC, pF = p2g_particle_reverse(s, a, f, p)
        adj_x += px
        adj_v = pv
        adj_C = pC
        adj_F += pF
        if f % s.stride == 0:
            add_own(a.adj_F_pc, f // s.stride, p, adj_F)  # dL/dF_pc^k += dL/dF_p^f (eq 55)
        check_particle_reverse(s, a, f, p, adj_x, adj_v, adj_C, adj_F)
    else:
        adj_v = a.adj_v[dst, p]
        adj_C = a.adj_C[dst, p]
    if f > f0:
        gx, gF = g2p_particle_reverse(s, a, f - 1, p, lane, adj_x, adj_v, adj_C, adj_F)
        a.adj_x[(f - 1) % 2, p] = gx
        a.adj_F[(f - 1) % 2, p] = gF
    else:
        a.adj_x[dst, p] = adj_x
        a.adj_v[dst, p] = adj_v
        a.adj_C[dst, p] = adj_C
        a.adj_F[dst, p] = adj_F
        zero_particle(a, (f + 1) % 2, p)


@ti.func
def step_loops_reverse(s: ti.template(), a: ti.template(), f, f0, f1):
    """Reverse step f of a pass from f1 down to f0 (f = f1: its start): the reverse grid operations, then one
    particle loop, reverse P2G and the check of step f and reverse G2P of step f - 1 (particle_adjoint).

    The forward's loops in reverse order; reverse G2P scatters into dL/dv_i as forward P2G scatters into m_i, p_i,
    with the same private grids per thread (lanes).
    """
    if ti.static(s.lanes > 0):  # the grid loop over the active boxes of steps f and f - 1 (mls_mpm.active)
        b0, b1 = reverse_box(s, f, f0, f1)
        for k in range(volume(b0, b1)):
            grid_node_reverse(s, a, f, node_in(b0, b1, k), f0, f1)
    else:
        for I in ti.grouped(ti.ndrange(*s.grid_shape)):
            grid_node_reverse(s, a, f, I, f0, f1)
    if ti.static(s.lanes > 0):
        for item in range(s.lanes * LANE_TASK):  # one task per lane, one thread each: mls_mpm.state.LANE_TASK
            lane, lo, hi = lane_span(s, item)
            for p in range(lo, hi):
                particle_adjoint(s, a, f, p, lane, f0, f1)
    else:
        for p in range(n_live(s)):
            particle_adjoint(s, a, f, p, 0, f0, f1)


@ti.kernel
def substep_reverse(s: ti.template(), a: ti.template(), f: ti.i32, f0: ti.i32, f1: ti.i32):
    """Reverse step f of a pass from f1 down to f0 in one launch of parallel loops (twin of mls_mpm.step.substep)."""
    step_loops_reverse(s, a, f, f0, f1)


def run_parallel_reverse(s, a, f0, f1):
    """Reverse steps f1-1 down to f0 after the pass's start (f = f1), one launch each (twin of
    mls_mpm.step.run_parallel)."""
    for f in range(f1, f0 - 1, -1):
        substep_reverse(s, a, f, f0, f1)


@ti.kernel
def run_serial_reverse(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 after the pass's start, in one launch, serially (twin of run_serial; s.lanes
    must be 0)."""
    ti.loop_config(serialize=True)
    for k in range(f1 - f0 + 1):
        step_loops_reverse(s, a, f1 - k, f0, f1)
