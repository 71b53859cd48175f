"""Memory of a simulation, estimated before anything is allocated, and the up-front refusal of what would not fit.

The estimate counts every Taichi field a Simulator allocates (State, its LossGrids, the AdjointState with its
per-thread grids) and the numpy arrays made around them (the targets, the controls and their uploads), part
by part, so that a refusal names the part that does not fit and the scene key that sizes it.
"""
from dataclasses import dataclass

from .config import ConfigError
from .sizes import field_capacity

F64 = 8  # bytes of a numpy float64: the arrays the loss and the controls hold before upload
I64 = 8  # bytes of a fault code
SIZES = 3 * 4  # State.sizes: N and the lanes' shares of it, i32


@dataclass(frozen=True)
class Part:
    """One part of a simulation's memory: what it is, the scene keys to lower, its Taichi-field and numpy bytes."""

    what: str
    lower: str
    field_bytes: int
    numpy_bytes: int = 0

    @property
    def bytes(self):
        return self.field_bytes + self.numpy_bytes


def loss_grid_shapes(loss):
    """(res, channels, has_alpha) of each loss grid of a PositionLoss, MassLoss, ColorLoss or OTLoss (or None)."""
    return [(g.res, g.target.shape[-1], g.alpha is not None)
            for g in (loss.grids if loss is not None else ())]


def parts(cfg, n_particles, grids=(), position_loss=False, tape=False, capacity=None):
    """The parts of a Simulator's memory (tape=True: of the grad-enabled State that gradient_tape adds), its
    particle fields holding `capacity` particles (None: sizes.field_capacity; the Tape's copy: exactly N).

    grids: (res, channels, has_alpha) of each loss grid; a grid of 3 channels is a color loss, whose
    particles carry colours; position_loss: the particles carry target positions.
    """
    w = 8 if cfg.dtype == "f64" else 4
    T, n, K, d = cfg.steps, cfg.n_grid, cfg.n_controls, cfg.dim
    N = n_particles if tape else (field_capacity(d, n_particles) if capacity is None else capacity)
    nodes = n ** d  # the grid grows as n_grid^dim per stored step
    state = 2 * d + 2 * d * d  # x, v (d each), C, F (d^2 each) of one particle
    node = 1 + 2 * d  # m, p, v of one node
    stored = node if tape else 1 + d  # per stored step: m, p, v under the Tape; m, p with one velocity slot
    sq = "^3" if d == 3 else "^2"
    copies = 2 if tape else 1  # needs_grad doubles every differentiated field
    colors = any(ch == 3 for _, ch, _ in grids)
    out = [
        Part(f"the particle states (x, v, C, F) of {T + 1} steps x {n_particles} particles",
             "sim.steps or sim.particles_per_cell",
             copies * (T + 1) * N * state * w),
        Part(f"the grid states ({'m, p, v' if tape else 'm, p'}) of {T} steps on the {n}{sq} grid",
             "sim.n_grid (in 3D the grid grows as n_grid^3 per stored step) or sim.steps" if d == 3 else
             "sim.n_grid or sim.steps",
             # + (without the Tape) the one velocity slot and the adjoint's grid
             copies * T * nodes * stored * w + (0 if tape else nodes * (d + node) * w)),
    ]
    lanes = 0 if tape else cfg.lanes(n_particles)
    if lanes:  # forward private grids (m, p) and the adjoint's (dL/dv); one step's G_p (State.G_step); the barrier's
        # counters (State.sync, State.progress: state.PROGRESS_LINE = 16 a lane, mls_mpm/persistent.py); the active
        # boxes of every step and lane (State.box, State.lane_box: 2 dim i32 each, mls_mpm/active.py)
        out.append(Part(f"the {lanes} per-thread grids of {n}{sq} nodes", "sim.n_grid or sim.threads",
                        lanes * nodes * (1 + 2 * d) * w + N * d * d * w + 4 * (3 + 16 * lanes)
                        + 4 * 2 * d * (T + lanes)))
    if grids:
        field = numpy = 0
        for res, ch, has_alpha in grids:
            # m (and its grad under the Tape, else the adjoint dL/dm), target (OT grids: the seed dL/dm), alpha;
            # numpy: target, alpha in f64 (OT grids keep theirs in numpy; their Sinkhorn work arrays are transient)
            field += res ** d * (3 * ch + has_alpha) * w
            numpy += res ** d * (ch + has_alpha) * F64
        numpy += max(res ** d * ch for res, ch, _ in grids) * w  # the upload's cast copy of one target
        out.append(Part(f"the loss grids loss.grids = [{', '.join(str(r) for r, _, _ in grids)}]", "loss.grids",
                        field, numpy))
    per_particle = (3 * colors + d * position_loss) * w  # colours c_p, target positions x_pu
    controls = K * N * d * d
    if tape:
        # F_pc and its grad, loss, faults, the count (State.sizes)
        field = 2 * controls * w + N * per_particle + 2 * w + 2 * I64 + SIZES
        numpy = controls * (w + 2 * F64) + N * state * F64  # the controls' upload, the gradient, the state of step 0
    else:
        # F_pc, dL/dF_pc, the adjoint's two particle slots (x, v, C, F), loss, faults, the count (State.sizes)
        field = 2 * controls * w + N * (2 * state * w + per_particle) + w + 3 * I64 + SIZES
        # the caller's controls, a trial or gradient copy and the returned gradient (f64), the upload's cast copy;
        # step 0's arrays (f64 and the cast): N particles' worth, whatever the fields' capacity
        live = K * n_particles * d * d
        numpy = live * (3 * F64 + w) + n_particles * state * (F64 + w)
    out.append(Part(f"the controls ({K} x {n_particles} particles) and adjoints",
                    "sim.particles_per_cell or steps / sim.stride", field, numpy))
    return out


def estimate_bytes(cfg, n_particles, grids=(), position_loss=False, tape=False, capacity=None):
    """Bytes a Simulator allocates (tape=True: what gradient_tape adds), Taichi fields and numpy copies."""
    return sum(p.bytes for p in parts(cfg, n_particles, grids, position_loss, tape, capacity))


def available_bytes():
    """Memory the system can still give (MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def limit(cfg):
    """(bytes, words) a run may allocate: sim.max_memory_gb when set, else 90% of the memory available now;
    (None, "") where that is unknown. The one rule for the simulation, the scene's sampling and the renderer."""
    if cfg.max_memory_gb:
        return cfg.max_memory_gb * 2 ** 30, f"sim.max_memory_gb = {cfg.max_memory_gb:g}"
    free = available_bytes()
    return (0.9 * free, "90% of the memory available; sim.max_memory_gb sets it") if free else (None, "")


def check_memory(cfg, n_particles, grids=(), where="", position_loss=False, tape=False, capacity=None):
    """Refuse, before allocating, what would not fit (cfg.max_memory_gb, else 90% of what is free now); return the
    particle capacity the fields are to hold: sizes.field_capacity, or exactly n_particles where only that fits (the
    capacity's padding is never the reason for a refusal).

    grids: (res, channels, has_alpha) of each loss grid; where: a prefix naming the scene file, or "";
    n_particles may be an upper bound (a scene checked before its image is sampled). tape=True checks the
    grad-enabled State of gradient_tape, on top of a Simulator already allocated, whose fields hold `capacity`.
    """
    allowed, _ = limit(cfg)
    if allowed is not None and cfg.max_memory_gb and tape:  # the Simulator's own fields are already allocated
        allowed -= estimate_bytes(cfg, n_particles, grids, position_loss, capacity=capacity)
    if capacity is None:
        capacity = field_capacity(cfg.dim, n_particles)
    ps = parts(cfg, n_particles, grids, position_loss, tape, capacity)
    need = sum(p.bytes for p in ps)
    if allowed is not None and need > allowed and not tape and capacity > n_particles:  # without the padding
        capacity = n_particles
        ps = parts(cfg, n_particles, grids, position_loss, tape, capacity)
        need = sum(p.bytes for p in ps)
    if allowed is not None and need > allowed:
        big = max(ps, key=lambda p: p.bytes)
        what = "the Tape's grad-enabled fields (gradient_tape) need" if tape else "the simulation needs"
        f32 = ", use sim.dtype = f32" if cfg.dtype == "f64" else ""
        raise ConfigError(f"{where}{what} about {need / 2 ** 30:.2f} GiB ({cfg.steps} steps, {n_particles} "
                          f"particles, a {cfg.n_grid}^{cfg.dim} grid, {cfg.dtype}), above the limit of "
                          f"{max(allowed, 0) / 2 ** 30:.3g} GiB; the largest part is {big.what} "
                          f"({big.bytes / 2 ** 30:.2f} GiB): lower {big.lower}{f32}, or raise sim.max_memory_gb")
    return capacity
