"""Preallocated fields of one simulation: every step's particle and grid state, time an explicit axis."""

import numpy as np
import taichi as ti

from .losses import OT_KINDS, ColorLoss, PositionLoss
from .runtime import real
from .sizes import lane_chunk, lane_item, n_live

FAULT_NONE = 2 ** 62  # fault[k] holds min(f * N + p) over faulty (step f, particle p), or this
FAULT_LEFT_GRID = 0  # a particle's 4x4 stencil left the grid
FAULT_NON_FINITE = 1  # a particle's new state holds NaN or Inf


@ti.data_oriented
class LossGrid:
    """One loss grid of its own resolution (thesis 8.1): its mass (and color-mass) and target.

    kind: "mass" (eq 11 / 72), "log_mass" (1/2 (ln(m+1) - ln(m_u+1))^2), "color" (eq 13), "ot" (the
    Sinkhorn divergence of losses.OTLoss, computed in numpy from m; its target stays in numpy, and the field
    `seed` holds its gradient dL/dm_i in place of the target field) or "color_ot" (the same per colour
    channel, ColorLoss's ot_weights). Entry [i, j] (3D: [i, j, k]) is the node at (i dx, j dx[, k dx])
    with dx = 1 / res; the grid has res^dim nodes.
    """

    def __init__(self, dtype, dim, kind, res, weight, has_alpha, needs_grad=False, needs_adjoint=False, blur=0.0,
                 reach=None, tol=0.0):
        self.kind = kind
        self.dim = dim
        self.shape = (res,) * dim
        self.np_dtype = np.float64 if dtype == ti.f64 else np.float32
        self.blur, self.reach, self.tol = blur, reach, tol  # OT grids only
        self.target_np = None  # OT grids: the target masses m_iu (res,) * dim, set by upload_loss
        self.res = res
        self.dx = 1.0 / res
        self.inv_dx = float(res)
        self.weight = float(weight)
        self.has_alpha = has_alpha
        self.is_color = kind in ("color", "color_ot")
        channels = 3 if self.is_color else 1
        self.channels = channels
        # m: node mass (color-mass c_i for color grids, eq 12); target: m_iu or c_iu
        self.m = ti.Vector.field(channels, dtype, shape=self.shape, needs_grad=needs_grad)
        if kind in OT_KINDS:
            self.seed = ti.Vector.field(channels, dtype, shape=self.shape)  # dL/dm_i of the last ot_loss
        else:
            self.target = ti.Vector.field(channels, dtype, shape=self.shape)
        if has_alpha:
            self.alpha = ti.field(dtype, shape=self.shape)  # penalty alpha_i of eq 72
        if needs_adjoint:
            self.adj_m = ti.Vector.field(channels, dtype, shape=self.shape)  # dL/dm_i (eq 41)


# A lane loop (`for item in range(s.lanes * LANE_TASK)`, lane_span) runs each lane's particles as LANE_TASK items.
# Taichi 1.7's CPU range-for cuts a loop of n items into tasks of min(1024, max(512, n / (32 threads))) items, which
# its threads take in turn (cpu_block_dim_adaptive, on by default and set by runtime.ensure; it overrides
# ti.loop_config(block_dim)): a loop over the `lanes` lanes themselves was one task, run by one thread, one lane after
# the other. Here n / (32 threads) = 16 items (lanes = threads), so the tasks are of 512 items, one per lane: each
# thread scatters one lane's particles, in index order, into that lane's private grid, and no two threads share one.
LANE_TASK = 512
# State.progress gives each lane a row of PROGRESS_LINE i32 counters (64 bytes, a cache line's size), of which the lane
# ticks the first (persistent.tick), so that lanes never tick the same line. That one shared counter cost time was
# not shown: the 5% that 6ec0b0b removed came from ticking inside the loop bodies, with either kind of counter.
PROGRESS_LINE = 16


@ti.func
def lane_span(s: ti.template(), item):
    """The lane of item `item` of a lane loop and its particles lo..hi-1: the lane's share of lane_chunk particles
    cut into LANE_TASK runs of lane_item, in index order (a run past the lane's last particle is empty)."""
    lane = item // LANE_TASK
    end = ti.min((lane + 1) * lane_chunk(s), n_live(s))
    lo = ti.min(lane * lane_chunk(s) + (item % LANE_TASK) * lane_item(s), end)
    return lane, lo, ti.min(lo + lane_item(s), end)


@ti.func
def pack_mp(p, m):
    """(p, m) as one (dim + 1)-vector, momentum (or its adjoint) first and mass last: a node of State.grid_mp,
    State.lane_mp and AdjointState.adj_grid_mp, its dim + 1 values adjacent in memory."""
    return ti.Vector([p[d] for d in ti.static(range(p.n))] + [m])


@ti.func
def unpack_mp(q):
    """(p, m) from a pack_mp vector q."""
    return ti.Vector([q[d] for d in ti.static(range(q.n - 1))]), q[q.n - 1]


def pack_mp_np(p, m):
    """pack_mp of numpy arrays: p (..., dim) and m (...) as one (..., dim + 1) array, for a field of that layout."""
    return np.concatenate([p, np.asarray(m)[..., None]], axis=-1)


def unpack_mp_np(q):
    """unpack_mp of a numpy array q (..., dim + 1), a field of pack_mp's layout read back: (p, m)."""
    return q[..., :-1], q[..., -1]


@ti.data_oriented
class State:
    """Fields of one simulation; per-step fields are shaped (steps + 1, ...) or (steps, ...) for the grid.

    Scalars stored here (dx, dt, mu, ...) are compile-time constants of the kernels that take the state, except the
    particle count and the lanes' shares of it (sizes: read at run time). The particle fields hold `capacity`
    particles (default n_particles; Simulator: particle_capacity), of which the first n_particles are simulated.
    """

    def __init__(self, cfg, n_particles, loss_grids=(), position_loss=False, colors=False, needs_grad=False,
                 lanes=0, every_velocity=False, capacity=None):
        dt_ = real(cfg.dtype)
        T = cfg.steps
        d = self.dim = cfg.dim
        self.n_particles = n_particles  # host code's; kernels read n_live(s)
        self.capacity = n_particles if capacity is None else capacity
        if self.capacity < n_particles:
            raise ValueError(f"State: capacity {self.capacity} < {n_particles} particles")
        self.steps = T
        self.n_grid = cfg.n_grid
        self.dx = cfg.dx
        self.inv_dx = cfg.inv_dx
        self.dt = cfg.dt
        self.vol = cfg.vol
        self.m_p = cfg.m_p
        self.mu = cfg.mu
        self.lam = cfg.lam
        self.gamma = cfg.gamma
        self.gravity = cfg.gravity
        self.sticky = cfg.boundary == "sticky"
        self.bound = cfg.bound
        self.stride = cfg.stride
        self.n_controls = cfg.n_controls
        # the loss kernels' loops run serially on a CPU, so that their sums have one order (a bit-identical loss
        # and gradient run after run); on a GPU they stay parallel
        self.serial_losses = cfg.arch == "cpu"
        # lanes > 0: P2G scatters into `lanes` private grids, one per CPU thread, summed by the grid loop
        # (no float atomics); 0: atomic adds straight into grid f (GPUs, the serial schedule, the Tape)
        self.lanes = lanes
        self.lane_chunk = -(-n_particles // max(lanes, 1))  # particles per lane
        self.lane_item = -(-self.lane_chunk // LANE_TASK)  # particles per item of a lane loop (lane_span)
        # eq 17 divides by m_i + m_eps: zero at empty nodes, nowhere a cut; in f32 large enough that m_eps^2 (in
        # the Tape's derivative of the quotient) does not underflow to 0, still far below f32's resolution
        self.m_eps = (1e-20 if cfg.dtype == "f64" else 1e-12) * cfg.m_p
        g = needs_grad
        N = self.capacity
        grid = self.grid_shape = (cfg.n_grid,) * d  # n_grid^dim nodes
        self.x = ti.Vector.field(d, dt_, shape=(T + 1, N), needs_grad=g)  # position x_p^n
        self.v = ti.Vector.field(d, dt_, shape=(T + 1, N), needs_grad=g)  # velocity v_p^n
        self.C = ti.Matrix.field(d, d, dt_, shape=(T + 1, N), needs_grad=g)  # affine velocity C_p^n (eq 19)
        self.F = ti.Matrix.field(d, d, dt_, shape=(T + 1, N), needs_grad=g)  # deformation gradient F_p^n
        self.F_pc = ti.Matrix.field(d, d, dt_, shape=(self.n_controls, N), needs_grad=g)  # control F_pc (eq 8)
        # grid state of steps 0..T-1 (step T has no grid update)
        # node (p_i^n, m_i^n) (eq 16, 15) in one (dim + 1)-vector, pack_mp's layout: one address a node for the
        # scatter, the grid loop and the reverse pass (grid_mass / grid_momentum split it in numpy)
        self.grid_mp = ti.Vector.field(d + 1, dt_, shape=(T,) + grid, needs_grad=g)
        # node velocity v_i^n (eq 17): every step under the Tape (needs_grad) or where asked (every_velocity, the
        # kernel tests), else one slot that the grid loop of each step overwrites and the reverse pass recomputes
        # from m_i, p_i (adjoint.step): (1 + 2 dim) / (1 + dim) the grid memory of a step otherwise
        self.every_velocity = g or every_velocity
        self.grid_v = ti.Vector.field(d, dt_, shape=((T if self.every_velocity else 1),) + grid, needs_grad=g)
        if lanes:
            self.lane_mp = ti.Vector.field(d + 1, dt_, shape=(lanes,) + grid)  # private node (p, m) of one thread
            self.G_step = ti.Matrix.field(d, d, dt_, shape=N)  # G_p of the step being scattered (step.step_loops)
            self.sync = ti.field(ti.i32, shape=3)  # persistent.barrier: arrivals, the give-up flag, slow waits
            self.progress = ti.field(ti.i32, shape=(lanes, PROGRESS_LINE))  # persistent.tick: each lane's work
            # active.py: the nodes [lo, hi) each step's particles touch (the grid loops' range), and each lane's share
            # of the step being scattered (persistent.run_persistent); every node until a pass sets them
            self.box = ti.field(ti.i32, shape=(T, 2, d))
            every = np.zeros((T, 2, d), np.int32)
            every[:, 1] = cfg.n_grid
            self.box.from_numpy(every)
            self.lane_box = ti.field(ti.i32, shape=(lanes, 2, d))
        self.loss = ti.field(dt_, shape=(), needs_grad=g)
        self.fault = ti.field(ti.i64, shape=2)  # least faulty f * N + p per FAULT_* kind
        self.has_colors = colors
        if colors:
            self.color = ti.Vector.field(3, dt_, shape=N)  # particle RGB c_p (eq 12)
        self.has_position_loss = position_loss
        if position_loss:
            self.target_x = ti.Vector.field(d, dt_, shape=N)  # x_pu of eq 10
        self.loss_grids = [
            LossGrid(dt_, d, lg.kind, lg.res, lg.weight, lg.alpha is not None, needs_grad=g, needs_adjoint=not g,
                     blur=lg.blur, reach=lg.reach, tol=lg.tol)
            for lg in loss_grids
        ]
        self.active_grids = list(self.loss_grids)  # the loss grids whose terms the loss sums (schedule stages)
        self.sizes = ti.field(ti.i32, shape=3)  # N, lane_chunk, lane_item: what the kernels read of the count
        self.sizes.from_numpy(np.array([n_particles, self.lane_chunk, self.lane_item], np.int32))

    def grid_mass(self):
        """m_i^n of steps 0..T-1 in numpy, shaped (T,) + grid_shape."""
        return unpack_mp_np(self._grid_mp())[1]

    def grid_momentum(self):
        """p_i^n of steps 0..T-1 in numpy, shaped (T,) + grid_shape + (dim,)."""
        return unpack_mp_np(self._grid_mp())[0]

    def _grid_mp(self):
        """grid_mp in numpy, zero outside each step's active box (with lanes the grid loops leave an earlier pass's
        values there, which no kernel reads: active.py)."""
        q = self.grid_mp.to_numpy()
        if self.lanes:
            box = self.box.to_numpy()
            for f in range(self.steps):
                keep = np.zeros(self.grid_shape, bool)
                keep[tuple(slice(lo, max(lo, hi)) for lo, hi in zip(box[f, 0], box[f, 1]))] = True
                q[f][~keep] = 0.0
        return q

    def clear_faults(self):
        self.fault.from_numpy(np.full(2, FAULT_NONE, dtype=np.int64))

def upload_loss(s, loss, grids=None):
    """Copy a loss's targets (and particle colors / target positions) into the state's fields.

    grids: the state's loss grids that hold this loss's terms (default: all of them, a state made for this loss)."""
    if loss is None:
        return
    np_dtype = np.float64 if s.x.dtype == ti.f64 else np.float32
    for g, spec in zip(s.loss_grids if grids is None else grids, loss.grids):
        if g.kind in OT_KINDS:
            g.target_np = spec.target[..., 0] if g.kind == "ot" else spec.target
            continue
        g.target.from_numpy(spec.target.astype(np_dtype))
        if spec.alpha is not None:
            g.alpha.from_numpy(spec.alpha.astype(np_dtype))
    if isinstance(loss, PositionLoss):
        s.target_x.from_numpy(padded(loss.target.astype(np_dtype), s.capacity))
    if isinstance(loss, ColorLoss):
        s.color.from_numpy(padded(loss.colors.astype(np_dtype), s.capacity))


def padded(rows, capacity):
    """rows (N, ...) as a particle field of `capacity` entries holds them: rows N.. zero."""
    if len(rows) == capacity:
        return rows
    out = np.zeros((capacity,) + rows.shape[1:], rows.dtype)
    out[:len(rows)] = rows
    return out


@ti.kernel
def write_step(s: ti.template(), f: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
               C: ti.types.ndarray(), F: ti.types.ndarray()):
    for p in range(n_live(s)):
        for d in ti.static(range(s.dim)):
            s.x[f, p][d] = x[p, d]
            s.v[f, p][d] = v[p, d]
            for e in ti.static(range(s.dim)):
                s.C[f, p][d, e] = C[p, d, e]
                s.F[f, p][d, e] = F[p, d, e]


@ti.kernel
def write_rows(s: ti.template(), field: ti.template(), values: ti.types.ndarray()):
    """field[k, p] = values[k, p] for the simulated particles p < N of a (K, capacity) matrix field (F_pc) from a
    (K, N, dim, dim) array: an upload into fields of a larger capacity (sizes.py) without a padded copy."""
    for k, p in ti.ndrange(field.shape[0], n_live(s)):
        for i, j in ti.static(ti.ndrange(s.dim, s.dim)):
            field[k, p][i, j] = values[k, p, i, j]


@ti.kernel
def read_rows(s: ti.template(), field: ti.template(), values: ti.types.ndarray()):
    """values[k, p] = field[k, p] for p < N (the reverse of write_rows; a float64 array gets the cast entries)."""
    for k, p in ti.ndrange(field.shape[0], n_live(s)):
        for i, j in ti.static(ti.ndrange(s.dim, s.dim)):
            values[k, p, i, j] = field[k, p][i, j]


@ti.kernel
def write_x(s: ti.template(), f: ti.i32, x: ti.types.ndarray()):
    """Replace the positions of step f alone."""
    for p in range(n_live(s)):
        for d in ti.static(range(s.dim)):
            s.x[f, p][d] = x[p, d]


@ti.kernel
def read_step(s: ti.template(), f: ti.i32, x: ti.types.ndarray(), v: ti.types.ndarray(),
              C: ti.types.ndarray(), F: ti.types.ndarray()):
    for p in range(n_live(s)):
        for d in ti.static(range(s.dim)):
            x[p, d] = s.x[f, p][d]
            v[p, d] = s.v[f, p][d]
            for e in ti.static(range(s.dim)):
                C[p, d, e] = s.C[f, p][d, e]
                F[p, d, e] = s.F[f, p][d, e]
