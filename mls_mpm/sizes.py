"""The particle count as the kernels see it: a value read at run time, and the capacity the particle fields hold.

The particle count N is not compiled into the kernels: they read it, and the lanes' shares of it, from State.sizes
at run time, and a 3D Simulator's particle fields are shaped for particle_capacity(N), one of a few sizes (4 a
doubling), their entries beyond N untouched (zero). A new shape whose count has the same capacity (and the same
settings) then builds the same kernels, which Taichi's offline cache holds from the last run: a new initial shape
needs no compile (3D: about 5 s a new shape). At most 19% more particle memory (memory.parts counts it); 2D fields
hold exactly N (field_capacity).
"""
import taichi as ti

CAPACITY_BASE = 64  # the least capacity (before the spread below)
CAPACITY_STEPS = 4  # capacities per doubling
# A particle field holds step f's entries at f * capacity * entry bytes. Where that stride is (near) a multiple of
# 4 KiB, one particle's entries of consecutive steps fall into the same L1 cache sets, and the reverse pass, which
# reads steps f - 1, f and f + 1 together, ran 7-10% slower (3D, a capacity of 16,384: BENCHMARKS.md, "Kernels
# cached across particle counts"). So a capacity is moved up to the next count whose strides of one and two steps
# lie at least CACHE_SPREAD bytes from a multiple of CACHE_PAGE, for the bytes of every particle entry: x, v, target
# x (dim floats), colour (3), C, F, F_pc, G (dim^2), in f32 and f64, 2D and 3D.
CACHE_PAGE = 4096
CACHE_SPREAD = 256
ENTRY_BYTES = (8, 12, 16, 24, 32, 36, 72)


def spread(capacity: int) -> int:
    """The least distance, in bytes, of a one- or two-step stride of a particle field of this capacity from a
    multiple of CACHE_PAGE, over ENTRY_BYTES."""
    return min(min(r, CACHE_PAGE - r) for e in ENTRY_BYTES for j in (1, 2)
               for r in [j * capacity * e % CACHE_PAGE])


def particle_capacity(n: int) -> int:
    """The particle count a Simulator's fields hold for n particles: for the least k with
    t = int(CAPACITY_BASE 2^(k / CAPACITY_STEPS)) >= n, the least count >= t whose spread is at least CACHE_SPREAD
    (at most about 40 more). A function of k alone, so every n of one k gets the same fields and kernels."""
    k = 0
    while int(CAPACITY_BASE * 2.0 ** (k / CAPACITY_STEPS)) < n:
        k += 1
    capacity = int(CAPACITY_BASE * 2.0 ** (k / CAPACITY_STEPS))
    while spread(capacity) < CACHE_SPREAD:
        capacity += 1
    return capacity


def field_capacity(dim: int, n: int) -> int:
    """The particles a Simulator's fields hold by default: particle_capacity(n) in 3D, where a new shape's compile
    costs about 5 s (a 3D fast preview of a new shape took 1.6x as long); n itself in 2D, where it costs about 1.5 s
    and padding would cost up to 19% of the particle memory, which long 2D scenes fill (the f64 thesis size: 40 MiB
    in fields of 1,456 against 36 for its 1,245 particles; BENCHMARKS.md, "Kernels cached across particle counts").
    memory.check_memory falls back to n where the capacity would not fit."""
    return particle_capacity(n) if dim == 3 else n


@ti.func
def n_live(s: ti.template()):
    """N, the particles state s simulates (a run-time value: its fields may hold more, see particle_capacity)."""
    return s.sizes[0]


@ti.func
def lane_chunk(s: ti.template()):
    """The particles of one lane (State.lane_chunk, read at run time)."""
    return s.sizes[1]


@ti.func
def lane_item(s: ti.template()):
    """The particles of one item of a lane loop (State.lane_item, read at run time)."""
    return s.sizes[2]
