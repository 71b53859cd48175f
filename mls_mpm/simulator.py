"""Simulator: orchestrates the forward kernels, the hand-written reverse pass and the Tape oracle."""

import functools
import math

import numpy as np

from adjoint.losses import evaluate_reverse
from adjoint.persistent import persistent_pass_reverse
from adjoint.state import AdjointState
from adjoint.step import run_parallel_reverse, run_serial_reverse

from . import losses, runtime
from .config import ConfigError
from .errors import SimulationError
from .losses import ColorLoss, PositionLoss
from .memory import check_memory, loss_grid_shapes
from .persistent import persistent_pass
from .state import (FAULT_LEFT_GRID, FAULT_NON_FINITE, FAULT_NONE, State, read_rows, read_step, upload_loss, write_rows,
                    write_step, write_x)
from .step import clear_grid, run_parallel, run_serial
from .tape import tape_gradient, tape_gradients_in_child
from .transfer import check_step


PERSISTENT_BACKOFF = 8  # passes with a launch per step after a one-launch pass gave up (Simulator._pass)


def _live(method):
    """Refuse to run a Simulator method once Taichi was re-initialised (its fields are freed)."""
    @functools.wraps(method)
    def checked(self, *args, **kwargs):
        runtime.RUNTIME.check(self._generation, self._built_for)
        return method(self, *args, **kwargs)
    return checked


def _check_backend(cfg, loss):
    """Refuse what the running backend cannot compile: Taichi's SPIR-V (Vulkan) has no 64-bit log."""
    if runtime.running_arch() == "vulkan" and cfg.dtype == "f64" and any(g.kind == "log_mass" for g in loss.grids):
        raise ConfigError("loss.kind = log_mass needs a 64-bit log, which Taichi's Vulkan backend cannot compile; "
                          "use sim.dtype = f32, loss.kind = mass, or sim.arch = cpu or cuda")


def tape_refused(cfg):
    """Why the ti.ad.Tape oracle cannot be trusted on the running backend for cfg, or None: on Vulkan in 3D, Taichi
    1.7.4's Tape disagreed with the manual gradient by 98% (lavapipe) while the manual gradient matched central
    differences and the CPU's (tests/test_gpu.py)."""
    if cfg.dim == 3 and runtime.running_arch() == "vulkan":
        return ("the ti.ad.Tape oracle gives wrong 3D gradients on Vulkan (Taichi 1.7.4; the manual gradient is right "
                "there, tests/test_gpu.py)")
    return None


def _largest_norm(controls):
    """The largest Frobenius norm |F_pc| over controls (K, N, dim, dim), scaled so that 1e200 does not overflow."""
    scale = float(np.max(np.abs(controls), initial=0.0))
    return scale * float(np.max(np.linalg.norm(controls / scale, axis=(2, 3)))) if scale > 0 else 0.0


def _check_dim(cfg, loss):
    """Refuse a loss whose targets have another dimension than the simulation."""
    dims = {loss.dim} if isinstance(loss, PositionLoss) else {g.dim for g in loss.grids}
    if dims - {cfg.dim}:
        what = "target_positions" if isinstance(loss, PositionLoss) else "targets"
        raise ValueError(f"loss {what}: {dims.pop()}D, but the simulation has dim = {cfg.dim}")


class Simulator:
    """A differentiable MLS-MPM simulation of N particles over cfg.steps steps.

    x0: (N, dim) initial positions (velocity 0, F = I, C = 0); loss: PositionLoss, MassLoss, ColorLoss, OTLoss
    or None, whose targets have cfg.dim dimensions.
    """

    def __init__(self, cfg, x0, loss=None):
        self._generation = runtime.ensure(cfg)
        self._built_for = str(runtime.RUNTIME.settings)
        self.cfg = cfg
        self.np_dtype = np.float64 if cfg.dtype == "f64" else np.float32
        self.dim = d = cfg.dim
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.ndim != 2 or x0.shape[1] != d or len(x0) == 0:
            raise ValueError(f"x0: expected shape (N, {d}) with N >= 1 (dim = {d}), got {x0.shape}")
        self.n_particles = len(x0)
        if loss is not None:
            loss.check(self.n_particles)
            _check_dim(cfg, loss)
            _check_backend(cfg, loss)
        # the particle capacity of the fields (sizes.field_capacity: the kernels of a 3D shape serve others of its
        # capacity), exactly N where only that fits
        capacity = check_memory(cfg, self.n_particles, grids=loss_grid_shapes(loss),
                                position_loss=isinstance(loss, PositionLoss))
        self.loss = loss
        # the schedule by whether the workers are to be pinned (config.pins_workers), not by whether the probe of
        # mls_mpm/affinity.py singled them out, which can fail on a busy machine: the same schedule, and so the same
        # round-off, in every run of these settings here (a failed probe leaves the threads unpinned, only slower)
        self._serial = cfg.serial(self.n_particles)
        self.fields = State(cfg, self.n_particles, loss_grids=loss.grids if loss else (),
                            position_loss=isinstance(loss, PositionLoss), colors=isinstance(loss, ColorLoss),
                            lanes=cfg.lanes(self.n_particles), capacity=capacity)
        upload_loss(self.fields, self.loss)
        self._adjoint = None
        self._start = 0
        self._stop = 0
        self._stored = 0  # stored steps 0.._stored hold one trajectory (a later forward may start there)
        self._forward_done = False  # the stored steps are those of the last forward, which succeeded
        self._backward_done = False  # the adjoints hold the last backward, which succeeded
        self._tape_state = None  # grad-enabled fields, allocated by the first gradient_tape call
        self._persistent_wait = 0  # passes to run with launches per step before one launch a pass is tried again
        self.set_initial(x0)

    @property
    def schedule(self):
        """The schedule this simulator steps in, "serial" or "parallel": cfg.schedule, or what `auto` resolved to."""
        return "serial" if self._serial else "parallel"

    def serves(self, cfg, n_particles) -> bool:
        """Whether this simulator can simulate cfg with n_particles particles now: the same settings and count, and
        built in the Taichi runtime that runs now (a re-initialisation frees its fields). render_run re-simulates a
        run with the run's own simulator so: its kernels, already built, are not built again."""
        if cfg != self.cfg or n_particles != self.n_particles:
            return False
        try:
            runtime.RUNTIME.check(self._generation, self._built_for)
        except runtime.StaleSimulatorError:
            return False
        return True

    @property
    def control_shape(self):
        return (self.cfg.n_controls, self.n_particles, self.dim, self.dim)

    def zero_controls(self):
        return np.zeros(self.control_shape)

    @_live
    def set_initial(self, x, v=None, C=None, F=None):
        """Set the state of step 0 (defaults: v = 0, C = 0, F = I). Used to chain animations (thesis 7.4)."""
        N, d = self.n_particles, self.dim
        x = self._particle_array(x, "x", (N, d))
        v = np.zeros((N, d)) if v is None else self._particle_array(v, "v", (N, d))
        C = np.zeros((N, d, d)) if C is None else self._particle_array(C, "C", (N, d, d))
        F = np.tile(np.eye(d), (N, 1, 1)) if F is None else self._particle_array(F, "F", (N, d, d))
        lo, hi = self.cfg.dx, 1.0 - 2.0 * self.cfg.dx  # the 4^dim stencil from floor(x/dx) - 1 stays on the grid
        outside = np.flatnonzero(np.any((x < lo) | (x >= hi), axis=1))
        if len(outside):
            p = outside[0]
            raise ValueError(f"x: particle {p} at {tuple(np.round(x[p], 6))} lies outside [{lo:g}, {hi:g}) where "
                             f"its stencil fits on the {'x'.join([str(self.cfg.n_grid)] * d)} grid")
        write_step(self.fields, 0, *(a.astype(self.np_dtype) for a in (x, v, C, F)))
        self._stored = 0
        self._forward_done = self._backward_done = False

    def set_active_grids(self, resolutions=None):
        """Sum only the loss grids of these resolutions from the next forward on (None: every grid); a stage of
        optimize.schedule. Refuses a resolution the loss has no grid of."""
        grids = self.fields.loss_grids
        if resolutions is None:
            self.fields.active_grids = list(grids)
        else:
            missing = set(resolutions) - {g.res for g in grids}
            if missing:
                raise ValueError(f"resolutions {sorted(missing)}: this loss has grids of {sorted({g.res for g in grids})}")
            self.fields.active_grids = [g for g in grids if g.res in set(resolutions)]
        self._forward_done = self._backward_done = False

    @_live
    def forward(self, controls, start=0):
        """Run steps start..N_t-1 with controls (K, N, dim, dim) of F_pc and return the loss of step N_t.

        A start > 0 reuses the stored state of step `start` from an earlier forward pass (controls
        before it must be unchanged); backward() then stops at that step too. A forward pass that raised
        kept the steps up to its own start, so one may start there again.
        """
        if not 0 <= start < self.cfg.steps:
            raise ValueError(f"start = {start}: expected a step in [0, {self.cfg.steps})")
        if start > self._stored:
            raise RuntimeError(f"forward(start={start}): step {start} is not stored from a successful forward pass "
                               f"(none yet, or the last one raised before it, or set_initial or evaluate_positions "
                               f"replaced the states); call forward(controls) from a start of at most {self._stored}")
        controls = self._controls(controls)
        s = self.fields
        self._forward_done = self._backward_done = False
        self._stored = start
        if s.capacity == self.n_particles:
            s.F_pc.from_numpy(controls)
        else:  # the first N rows of the capacity's (sizes.py), without a padded copy; the others stay zero
            write_rows(s, s.F_pc, controls)

        def begin():
            s.clear_faults()
            clear_grid(s, start)

        self._pass(begin, (run_serial, persistent_pass, run_parallel), s, start, self.cfg.steps)
        check_step(s, self.cfg.steps)
        self._raise_fault(s)
        self._start = start
        L = losses.evaluate(s, self.cfg.steps) if self.loss is not None else 0.0
        self._stored = self.cfg.steps
        self._forward_done = True
        return L

    @_live
    def backward(self, stop=None):
        """dL/dF_pc (K, N, dim, dim) of the last forward pass, from the hand-written reverse kernels.

        The reverse pass runs from step N_t down to `stop` (default: the last forward's start); controls
        acting before `stop` get zero gradient. Stored steps before the last forward's start must come from
        the same controls (as forward(start=...) requires).
        """
        self._require_loss()
        if not self._forward_done:
            raise RuntimeError("backward(): no successful forward pass to differentiate (none yet, or the last one "
                               "raised, or set_initial or evaluate_positions replaced its states); call "
                               "forward(controls) first")
        stop = self._start if stop is None else stop
        if not 0 <= stop < self.cfg.steps:
            raise ValueError(f"stop = {stop}: expected a step in [0, {self.cfg.steps})")
        self._backward_done = False
        a = self._adjoint_state()
        s = self.fields

        def begin():
            a.adj_F_pc.fill(0.0)
            a.fault[None] = -1
            evaluate_reverse(s, a, self.cfg.steps)

        schedules = (run_serial_reverse, persistent_pass_reverse, run_parallel_reverse)
        self._pass(begin, schedules, s, a, stop, self.cfg.steps)
        self._stop = stop
        fault = int(a.fault[None])
        if fault >= 0:  # the latest step, and in it the lowest particle (stored as N - 1 - p, see adjoint.step)
            f, q = divmod(fault, self.n_particles)
            p = self.n_particles - 1 - q
            raise SimulationError(f"backward, step {f}: particle {p} has a non-finite adjoint (NaN or Inf); likely "
                                  "cause: a forward state near a singularity or a gradient grown too large over a "
                                  "long horizon (try fewer steps, smaller controls or optimize.clip)")
        self._backward_done = True
        if s.capacity == self.n_particles:
            return a.adj_F_pc.to_numpy(dtype=np.float64)  # cast as it is copied: one array, not an f32 one and its cast
        grad = np.empty(self.control_shape)  # the first N rows of the capacity's, cast as they are copied
        read_rows(s, a.adj_F_pc, grad)
        return grad

    @property
    def grad_x0(self):
        """dL/dx of the step the last backward() stopped at (step 0 by default)."""
        return self._initial_adjoint("grad_x0", "adj_x")

    @property
    def grad_v0(self):
        """dL/dv of the step the last backward() stopped at (step 0 by default)."""
        return self._initial_adjoint("grad_v0", "adj_v")

    @_live
    def evaluate_positions(self, x):
        """Loss and dL/dx_p (eq 42-43) for final positions x (N, dim) placed at step N_t, without physics.

        The `positions` study of thesis 8.1 follows this gradient; it overwrites the stored x of step N_t
        (so backward() needs a new forward pass afterwards).
        """
        self._require_loss()
        x = self._particle_array(x, "x", (self.n_particles, self.dim))
        s = self.fields
        T = self.cfg.steps
        self._forward_done = self._backward_done = False
        self._stored = min(self._stored, T - 1)
        write_x(s, T, x.astype(self.np_dtype))
        L = losses.evaluate(s, T)
        a = self._adjoint_state()
        evaluate_reverse(s, a, T)
        return L, a.adj_x.to_numpy(dtype=np.float64)[T % 2, :self.n_particles]  # the fields may hold more (sizes.py)

    @_live
    def state(self, n):
        """Particle state of stored step n as numpy arrays."""
        if not 0 <= n <= self.cfg.steps:
            raise ValueError(f"n = {n}: expected a step in [0, {self.cfg.steps}]")
        N, d = self.n_particles, self.dim
        out = {k: np.zeros((N,) + shape, self.np_dtype) for k, shape in (("x", (d,)), ("v", (d,)), ("C", (d, d)),
                                                                        ("F", (d, d)))}
        read_step(self.fields, n, out["x"], out["v"], out["C"], out["F"])
        return {k: a.astype(np.float64) for k, a in out.items()}

    @_live
    def gradient_tape(self, controls, validation=False):
        """The same gradient as backward(), through ti.ad.Tape on the same forward kernels (a test oracle).

        Allocates a second, grad-enabled copy of the fields on first call (refused first if it would not fit). Where
        the running Taichi does not fit the Tape (runtime.RUNTIME.fits: in 3D, not initialised with
        runtime.ensure(cfg, tape=True) before building this Simulator; in float32, compiled with
        MLS_MPM_COMPILE=fast), the Tape runs in a child process that does (its kernels compile there, about a
        minute each call in 3D).
        """
        self._require_loss()
        why = tape_refused(self.cfg)
        if why:
            raise ConfigError(f"gradient_tape: {why}; use sim.arch = cpu or cuda")
        controls = self._controls(controls)
        if self._tape_state is None:
            check_memory(self.cfg, self.n_particles, grids=loss_grid_shapes(self.loss), capacity=self.fields.capacity,
                         position_loss=isinstance(self.loss, PositionLoss), tape=True)
        if not runtime.RUNTIME.fits(self.cfg, tape=True):  # re-initialising here would free this Simulator's fields
            return tape_gradients_in_child([(self.cfg, self.state(0), self.loss, controls)], validation)[0][1]
        _, grad, self._tape_state = tape_gradient(self.cfg, self.state(0), self.loss, controls, validation,
                                                  self._tape_state)
        return grad

    # helpers
    def _pass(self, begin, schedules, *args):
        """begin(), then a pass in this simulator's schedule; schedules: its (serial, one launch, launch per step)
        functions, each called with args. The parallel schedule on a CPU (lanes) runs in one launch
        (mls_mpm.persistent); a one-launch pass that gave up (other work held the CPUs) is begun again and run with
        a launch per step, as are the next PERSISTENT_BACKOFF passes."""
        serial, one_launch, parallel = schedules
        begin()
        if self._serial:
            serial(*args)
        elif not self.fields.lanes:
            parallel(*args)
        elif self._persistent_wait > 0:
            self._persistent_wait -= 1
            parallel(*args)
        elif not one_launch(*args):
            self._persistent_wait = PERSISTENT_BACKOFF
            begin()
            parallel(*args)

    def _initial_adjoint(self, name, field):
        runtime.RUNTIME.check(self._generation, self._built_for)
        if not self._backward_done:
            raise RuntimeError(f"{name}: no successful backward pass (none yet, it raised, or a forward pass ran "
                               "since); call backward() after forward(controls) first")
        return getattr(self._adjoint, field).to_numpy(dtype=np.float64)[self._stop % 2, :self.n_particles]

    def _adjoint_state(self):
        if self._adjoint is None:
            self._adjoint = AdjointState(self.fields, runtime.real(self.cfg.dtype))
        return self._adjoint

    def _require_loss(self):
        if self.loss is None:
            raise ValueError("this Simulator has no loss: pass loss=PositionLoss/MassLoss/ColorLoss to differentiate")

    def _in_dtype(self, a):
        """a cast to the simulation's dtype (no copy when it already is), overflow silent: 1e39 is Inf in f32."""
        with np.errstate(over="ignore", invalid="ignore"):
            return a.astype(self.np_dtype, copy=False)

    def _finite_in_dtype(self, a):
        """Where a stays finite once cast to the simulation's dtype."""
        return np.isfinite(self._in_dtype(a))

    def _particle_array(self, a, name, shape):
        a = np.asarray(a, dtype=np.float64)
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
        bad = np.argwhere(~self._finite_in_dtype(a))
        if len(bad):
            raise ValueError(f"{name}: particle {bad[0][0]} holds NaN or Inf (in {self.cfg.dtype})")
        return a

    def _controls(self, controls):
        """controls (K, N, dim, dim) in the simulation's dtype, their shape and finiteness there checked. One cast
        and one pass over them: on a GPU this host work is a large share of a short forward (BENCHMARKS.md)."""
        controls = np.asarray(controls, dtype=np.float64)
        if controls.shape != self.control_shape:
            raise ValueError(f"controls: expected shape {self.control_shape} (K, N, dim, dim), got {controls.shape}")
        cast = self._in_dtype(controls)
        finite = np.isfinite(cast)
        if not finite.all():
            k, p = np.argwhere(~finite)[0][:2]
            raise ValueError(f"controls: control {k} (step {k * self.cfg.stride}), particle {p} holds NaN or Inf (in {self.cfg.dtype})")
        return cast

    def _raise_fault(self, s):
        fault = s.fault.to_numpy()
        hits = [(int(fault[k]) // self.n_particles, k, int(fault[k]) % self.n_particles)
                for k in (FAULT_LEFT_GRID, FAULT_NON_FINITE) if fault[k] != FAULT_NONE]
        if hits:
            f, k, p = min(hits)
            raise SimulationError(f"step {f}: particle {p} {self._fault_cause(k, f, p)}")

    def _fault_cause(self, kind, f, p):
        """What went wrong with particle p at step f, and the likely cause the settings point to."""
        cfg = self.cfg
        cell_speed = cfg.dx / cfg.dt  # one cell per step
        g = math.hypot(*cfg.gravity)  # |g| in any dim
        causes = []
        if cfg.dt > cfg.cfl_dt:
            causes.append(f"dt = {cfg.dt:.6g} above the CFL limit {cfg.cfl_dt:.6g} for this E, nu and density "
                          "(lower sim.dt)")
        if g * max(f, 1) * cfg.dt > cell_speed:
            causes.append(f"gravity: |g| = {g:.3g} for {max(f, 1)} steps gives a speed of "
                          f"{g * max(f, 1) * cfg.dt:.3g}, "
                          f"above dx / dt = {cell_speed:.3g} (one cell per step; lower sim.gravity or sim.dt)")
        # the controls this forward pass ran (F_pc holds them), measured only here: 3 ms at 16k particles x 3
        # controls in 3D, a few per cent of a 30-step forward pass
        control_size = _largest_norm(self.fields.F_pc.to_numpy().astype(np.float64))
        if control_size > 0.5:
            causes.append(f"controls up to |F_pc| = {control_size:.3g}, enough to make F + F_pc singular "
                          "(use smaller controls or optimize.clip)")
        if kind == FAULT_LEFT_GRID:
            v = self.fields.v[f, p]
            speed = math.hypot(*(float(v[d]) for d in range(self.dim)))
            if not causes:
                causes.append(f"its speed {speed:.3g} at step {f} against dx / dt = {cell_speed:.3g} (one cell per "
                              "step): controls or velocities too large for dt, or walls (bound) too thin")
            return (f"left the simulation grid (its {'x'.join(['4'] * self.dim)} stencil would index outside it); "
                    "likely cause: "
                    + "; and ".join(causes))
        if not causes:
            causes.append(f"a singular control or a state grown too large (dt = {cfg.dt:.3g} is below the CFL "
                          f"limit {cfg.cfl_dt:.3g}, gravity and controls are moderate)")
        return "has a non-finite state (NaN or Inf); likely cause: " + "; and ".join(causes)
