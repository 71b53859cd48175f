"""Forward time stepping, f -> f + 1, in two schedules that share the same per-particle/per-node bodies.

Launch cost dominates small scenes (~50 us per parallel loop on 2 CPU threads), so:
- `substep(s, f)` (`run_parallel(s, f0, f1)` over a range): one launch per step, parallel loops (large scenes,
  GPUs);
- `run_serial(s, f0, f1)`: one launch for a whole range of steps, every loop serial (small scenes on a CPU).
Grid f + 1 is cleared by step f's grid loop, after nothing reads it, so each step needs no extra clear loop; with
lanes the grid loop runs over the step's active box only (active.py) and overwrites grid f there.
"""
import taichi as ti

from .active import empty_box, load_box, merge_box, node_in, store_box, volume, widen
from .grid import grid_op_node
from .sizes import n_live
from .state import LANE_TASK, lane_span
from .transfer import check_particle, g2p_particle, p2g_particle, particle_G


@ti.func
def clear_node(s: ti.template(), f, I):
    s.grid_mp[f, I] = ti.Vector.zero(float, s.dim + 1)


@ti.kernel
def clear_grid(s: ti.template(), f: ti.i32):
    """Zero grid f before the first step of a forward pass."""
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        clear_node(s, f, I)


@ti.func
def gather_lanes(s: ti.template(), f, I):
    """grid f = the sum of the threads' private grids, which are zeroed for the next step."""
    mp = ti.Vector.zero(float, s.dim + 1)
    for lane in ti.static(range(s.lanes)):
        mp += s.lane_mp[lane, I]
        s.lane_mp[lane, I] = ti.Vector.zero(float, s.dim + 1)
    s.grid_mp[f, I] = mp


@ti.func
def grid_node(s: ti.template(), f, I):
    """Grid operations of node I; then grid f + 1 is made ready for the next step's scatter."""
    if ti.static(s.lanes > 0):
        gather_lanes(s, f, I)
    grid_op_node(s, f, I)
    if ti.static(s.lanes == 0):
        if f + 1 < s.steps:
            clear_node(s, f + 1, I)


@ti.func
def step_loops(s: ti.template(), f):
    """Check and P2G (eq 14-16), grid operations (eq 17 + gravity + walls), G2P (eq 18-21) of step f.

    At a kernel's top level these are parallel loops. With lanes (CPU), each thread scatters its share of the
    particles into a private grid with plain adds, which the grid loop sums over the step's active box (active.py):
    float atomics (compare-and-swap on a CPU) would cost more than the whole step. There the stresses come first, in
    a loop of their own (into s.G_step): a tight loop overlaps one particle's long chain of dependent operations
    (the 3D polar decomposition) with the next one's, which the 4^dim-node scatter between them prevents.
    """
    if ti.static(s.lanes > 0):
        for _ in range(1):
            lo, hi = empty_box(s)
            store_box(s.box, f, lo, hi)  # box f empty, widened below by the particles of step f
        for p in range(n_live(s)):
            s.G_step[p] = particle_G(s, f, p)
        for item in range(s.lanes * LANE_TASK):  # one task per lane, one thread each: state.LANE_TASK
            lane, lo, hi = lane_span(s, item)
            b0, b1 = empty_box(s)
            for p in range(lo, hi):
                check_particle(s, f, p, p2g_particle(s, f, p, lane, s.G_step[p]))
                b0, b1 = widen(s, f, p, b0, b1)
            merge_box(s, f, b0, b1)
        b0, b1 = load_box(s, s.box, f)
        for k in range(volume(b0, b1)):  # the grid loop over the step's active box only (active.py)
            grid_node(s, f, node_in(b0, b1, k))
    else:
        for p in range(n_live(s)):
            check_particle(s, f, p, p2g_particle(s, f, p, 0, particle_G(s, f, p)))
        for I in ti.grouped(ti.ndrange(*s.grid_shape)):
            grid_node(s, f, I)
    for p in range(n_live(s)):
        g2p_particle(s, f, p)


@ti.kernel
def substep(s: ti.template(), f: ti.i32):
    """Step f in one launch of parallel loops."""
    step_loops(s, f)


def run_parallel(s, f0, f1):
    """Steps f0..f1-1, one launch of parallel loops each (substep)."""
    for f in range(f0, f1):
        substep(s, f)


@ti.kernel
def run_serial(s: ti.template(), f0: ti.i32, f1: ti.i32):
    """Steps f0..f1-1 in one launch, serially (s.lanes must be 0)."""
    ti.loop_config(serialize=True)
    for f in range(f0, f1):
        step_loops(s, f)
