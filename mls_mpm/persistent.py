"""The parallel schedule on a CPU in one launch a pass: each thread stays in the launch from the first step to the
last and meets the others at spin barriers between the loops of a step.

Each parallel loop launched on its own wakes the other CPUs and refills their caches: on a 2-CPU virtual machine,
whose idle CPUs halt, 0.03-0.09 ms a launch, more than a small step's loop costs (benchmarks/dispatch_cost.py,
BENCHMARKS.md "Issue 14"). Here lane l's thread takes one task of the launch (state.LANE_TASK items, of which the
first does the work) and runs, step after step: the stresses and the scatter of its own particles (lane_span's
share) into its private grid, widening its own box of their stencils, a barrier, the grid operations of its share of
the step's active box (the lanes' boxes joined: active.py; summing the private grids), a barrier, and G2P of its own
particles (the next step's first barrier orders it before the grid loop that reads what it scattered). The
per-particle and per-node bodies are step.py's, over the same shares in the same order, so the states equal those of
run_parallel bit for bit.

A barrier needs every lane's thread running at once. When they are not (other work holds the CPUs, or fewer threads
run than lanes), waits grow long while no lane gets on with its work: each lane ticks s.progress as it goes (every
PROGRESS_EVERY particles or nodes), and a wait counts its spins since the last tick it saw (SLOW_SPINS,
GIVE_UP_SPINS). A lane that is only slower (more particles in its share on an expensive branch of the 3D polar
decomposition, pages touched for the first time) keeps ticking, so the waits it causes do not count. After too
many, the launch gives up, every thread leaves at its next barrier, and the caller runs the pass again with
run_parallel, whose launches wait without spinning (persistent_pass, Simulator._pass).
"""
import taichi as ti

from .active import empty_box, load_box, node_in, store_box, volume, widen
from .sizes import lane_chunk, n_live
from .state import LANE_TASK
from .step import grid_node
from .transfer import check_particle, g2p_particle, p2g_particle, particle_G

# A barrier wait of more than SLOW_SPINS spins (about 1.7 ms of atomic reads on the 2-CPU machine of BENCHMARKS.md,
# where a wait normally takes microseconds and the first one of a launch, while the other CPU wakes, up to 0.1 ms)
# without a tick of s.progress means the lanes it waits for are off their CPUs; SLOW_WAITS of them in one pass (other
# work shares the CPUs: each costs a time slice of the scheduler) or one wait of GIVE_UP_SPINS without a tick (about
# 26 ms: fewer threads running than lanes) give up the launch. Counting all the spins of a wait instead, as before,
# took a lane's longer share of the work for absence: the 3D 32^3 / 16k backward (about 3 ms a lane between
# barriers) gave up its first pass, and then one pass in about six, with nothing else running (AMD EPYC, 2 threads).
SLOW_SPINS = 1 << 16
SLOW_WAITS = 8
GIVE_UP_SPINS = 1 << 20
# A lane ticks its own counter s.progress[lane, 0] after every PROGRESS_EVERY particles or nodes of its loops (an
# atomic add on a cache line of its own, state.PROGRESS_LINE), a few microseconds of work apart even in 2D; a waiting
# thread sums the counters once every PROGRESS_CHECK spins, so that its reads do not take the lines from the working
# lanes at every spin. Only changes of the sum count, so the counters are never reset. The loops run in chunks of
# PROGRESS_EVERY items, with the tick between chunks: a test and a tick inside the loop body made the 2D f32 64^2 /
# 8k forward 5% slower (1.00 without it, side by side, AMD EPYC), with one counter for all lanes or one each.
PROGRESS_EVERY = 64
PROGRESS_CHECK = 1 << 10


@ti.func
def chunks(lo, hi):
    """How many chunks of PROGRESS_EVERY items cover lo..hi-1 (the last one maybe shorter)."""
    return (hi - lo + PROGRESS_EVERY - 1) // PROGRESS_EVERY


@ti.func
def chunk(lo, hi, c):
    """Chunk c of lo..hi-1: its items c0..c1-1."""
    c0 = lo + c * PROGRESS_EVERY
    return c0, ti.min(c0 + PROGRESS_EVERY, hi)


@ti.func
def tick(s: ti.template(), lane):
    """Lane `lane` finished a chunk of its loop: its counter goes up by one (barrier)."""
    ti.atomic_add(s.progress[lane, 0], 1)


@ti.func
def work_done(s: ti.template()):
    """The sum of the lanes' ticks (atomic reads)."""
    total = 0
    for lane in ti.static(range(s.progress.shape[0])):
        total += ti.atomic_add(s.progress[lane, 0], 0)
    return total


@ti.func
def barrier(s: ti.template(), target):
    """Arrive (s.sync[0] += 1) and wait until `target` arrivals in all, or until some thread gave up (s.sync[1]);
    whether the pass goes on. s.sync[2] counts the pass's slow waits: SLOW_SPINS spins without a tick of s.progress
    (the lanes' work). Atomic reads (atomic_add of 0): the compiler may not hoist them out of the loop, and the
    seq_cst atomics order every thread's field writes before the barrier against its reads after it."""
    ti.atomic_add(s.sync[0], 1)
    seen = work_done(s)
    spins = 0  # since the last tick seen
    slow = False
    while ti.atomic_add(s.sync[0], 0) < target and ti.atomic_add(s.sync[1], 0) == 0:
        spins += 1
        if spins % PROGRESS_CHECK == 0:
            now = work_done(s)
            if now != seen:
                seen = now
                spins = 0
        if spins > SLOW_SPINS:
            slow = True
        if spins == GIVE_UP_SPINS:
            ti.atomic_add(s.sync[1], 1)
    if slow:
        if ti.atomic_add(s.sync[2], 1) + 1 >= SLOW_WAITS:
            ti.atomic_add(s.sync[1], 1)
    return ti.atomic_add(s.sync[1], 0) == 0


@ti.func
def own_nodes(s: ti.template(), lane, nodes):
    """Lane `lane`'s share of `nodes` nodes (a box's, active.volume), in row-major order: k0..k1-1 (active.node_in)."""
    share = (nodes + s.lanes - 1) // s.lanes
    k0 = ti.min(lane * share, nodes)
    return k0, ti.min(k0 + share, nodes)


@ti.func
def own_particles(s: ti.template(), lane):
    """Lane `lane`'s particles lo..hi-1: the share lane_span's LANE_TASK runs cover, in index order."""
    lo = ti.min(lane * lane_chunk(s), n_live(s))
    return lo, ti.min(lo + lane_chunk(s), n_live(s))


@ti.func
def lane_shares(s: ti.template(), item):
    """The lane whose task item `item` opens (item % LANE_TASK == 0) and its particles lo..hi-1."""
    lane = item // LANE_TASK
    lo, hi = own_particles(s, lane)
    return lane, lo, hi


@ti.func
def joined_box(s: ti.template(), f, lane):
    """Box f (active.py), the lanes' boxes of their own particles (s.lane_box, published by the barrier after the
    scatter) joined in lane order; lane 0 stores it for the reverse pass."""
    lo, hi = empty_box(s)
    for other in ti.static(range(s.lanes)):
        a, b = load_box(s, s.lane_box, other)
        lo, hi = ti.min(lo, a), ti.max(hi, b)
    if lane == 0:
        store_box(s.box, f, lo, hi)
    return lo, hi


@ti.kernel
def run_persistent(s: ti.template(), f0: ti.i32, f1: ti.i32):
    """Steps f0..f1-1 in one launch of s.lanes tasks (s.sync zero before it): step.step_loops' loops, each lane's share
    of them, with a barrier after the scatter and after the grid loop (the stresses in the scatter loop, not in a
    loop of their own as step_loops has them: the same values, 2x faster here in 2D)."""
    for item in range(s.lanes * LANE_TASK):
        if item % LANE_TASK == 0:
            lane, lo, hi = lane_shares(s, item)
            arrived = 0
            alive = True
            for f in range(f0, f1):
                if alive:
                    b0, b1 = empty_box(s)
                    for c in range(chunks(lo, hi)):  # the stress inline (a loop into s.G_step: 2x slower in 2D)
                        c0, c1 = chunk(lo, hi, c)
                        for p in range(c0, c1):
                            check_particle(s, f, p, p2g_particle(s, f, p, lane, particle_G(s, f, p)))
                            b0, b1 = widen(s, f, p, b0, b1)
                        tick(s, lane)
                    store_box(s.lane_box, lane, b0, b1)
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:  # the grid loop over the step's active box (active.py)
                    b0, b1 = joined_box(s, f, lane)
                    k0, k1 = own_nodes(s, lane, volume(b0, b1))
                    for c in range(chunks(k0, k1)):
                        c0, c1 = chunk(k0, k1, c)
                        for k in range(c0, c1):
                            grid_node(s, f, node_in(b0, b1, k))
                        tick(s, lane)
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:
                    for c in range(chunks(lo, hi)):
                        c0, c1 = chunk(lo, hi, c)
                        for p in range(c0, c1):
                            g2p_particle(s, f, p)
                        tick(s, lane)


def persistent_pass(s, f0, f1):
    """Steps f0..f1-1 of a state with lanes (the parallel schedule on a CPU) by run_persistent; whether it finished the
    pass. If a barrier gave up, the steps are partly done: the private grids are left zero, and the caller begins the
    pass again with run_parallel (Simulator._pass)."""
    s.sync.fill(0)
    run_persistent(s, f0, f1)
    if s.sync[1] == 0:
        return True
    s.lane_mp.fill(0.0)
    return False
