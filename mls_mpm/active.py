"""The active box of a step: the nodes its particles' stencils touch, where the grid loops of the CPU's parallel
schedule (lanes) run instead of over the whole grid.

Box f is [lo, hi) per axis: lo the least stencil base of the particles of step f on the grid, hi the greatest plus
STENCIL (a particle off the grid is skipped by P2G and G2P, so by the box too). Nothing outside it is scattered to or
gathered from at step f, so the grid operations there would compute v_i = 0 for no reader: a ball of 1,192 particles
(the 3D quality suite's shrink_ball) spends half of a 32^3 forward + backward step in the whole-grid loops
(benchmarks/grid_cost.py, BENCHMARKS.md). The forward stores each step's box in State.box (T, 2, dim); the reverse
pass visits box f (its reverse grid operations) joined with box f - 1 (v_i of step f - 1 recomputed there).

With lanes, grid_mp[f] and the velocity slot hold values of an earlier pass outside box f, which no kernel reads;
State.grid_mass and grid_momentum return zero there, as the whole-grid loops left it. Without lanes (the serial
schedule, GPUs, the Tape) the loops cover the whole grid, as before: there grid f + 1 is cleared by step f's loop.
"""
import taichi as ti

from .config import STENCIL
from .kernels import inside, stencil


@ti.func
def empty_box(s: ti.template()):
    """(lo, hi) of no node, which every particle's stencil widens."""
    return ti.Vector([s.n_grid] * s.dim, ti.i32), ti.Vector([0] * s.dim, ti.i32)


@ti.func
def widen(s: ti.template(), f, p, lo, hi):
    """(lo, hi) widened by particle p's stencil at step f if it lies on the grid."""
    base, _ = stencil(s.x[f, p], s.inv_dx)
    if inside(base, s.n_grid):
        lo = ti.min(lo, base)
        hi = ti.max(hi, base + STENCIL)
    return lo, hi


@ti.func
def store_box(field: ti.template(), i, lo, hi):
    """field[i] = (lo, hi): a box in a (..., 2, dim) i32 field (State.box by step, State.lane_box by lane)."""
    for d in ti.static(range(lo.n)):
        field[i, 0, d] = lo[d]
        field[i, 1, d] = hi[d]


@ti.func
def load_box(s: ti.template(), field: ti.template(), i):
    """(lo, hi) of field[i], as store_box wrote it."""
    lo, hi = empty_box(s)
    for d in ti.static(range(s.dim)):
        lo[d] = field[i, 0, d]
        hi[d] = field[i, 1, d]
    return lo, hi


@ti.func
def merge_box(s: ti.template(), f, lo, hi):
    """Box f joined with (lo, hi) (atomic min and max: the same under any parallel order)."""
    for d in ti.static(range(s.dim)):
        ti.atomic_min(s.box[f, 0, d], lo[d])
        ti.atomic_max(s.box[f, 1, d], hi[d])


@ti.func
def reverse_box(s: ti.template(), f, f0, f1):
    """The nodes the reverse grid loop of step f visits in a pass from f1 down to f0: box f (f < f1), joined, where
    v_i of step f - 1 is recomputed there (one velocity slot, f - 1 >= f0), with box f - 1."""
    lo, hi = empty_box(s)
    if f < f1:
        a, b = load_box(s, s.box, f)
        lo, hi = ti.min(lo, a), ti.max(hi, b)
    if ti.static(not s.every_velocity):
        if f - 1 >= f0:
            a, b = load_box(s, s.box, f - 1)
            lo, hi = ti.min(lo, a), ti.max(hi, b)
    return lo, hi


@ti.func
def volume(lo, hi):
    """Nodes in [lo, hi) (0 for an empty box)."""
    n = 1
    for d in ti.static(range(lo.n)):
        n *= ti.max(hi[d] - lo[d], 0)
    return n


@ti.func
def node_in(lo, hi, k):
    """Node of row-major position k of the box [lo, hi) (the last axis fastest, as ti.ndrange)."""
    I = lo
    r = k
    for e in ti.static(range(lo.n)):
        d = lo.n - 1 - e
        ext = hi[d] - lo[d]
        I[d] = lo[d] + r % ext
        r //= ext
    return I

