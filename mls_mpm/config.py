"""Simulation settings (thesis sections 3, 5.3, 6.1) as one frozen, validated dataclass."""
from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, fields
from .errors import UserError

BOUNDARIES = ("slip", "sticky")
DTYPES = ("f32", "f64")
ARCHS = ("cpu", "gpu", "cuda", "vulkan")
SCHEDULES = ("auto", "serial", "parallel")
SERIAL_BELOW = 4000  # particles + grid nodes under which "auto" runs serially on a CPU (3D, or over 2 threads)
# The same in 2D on 2 CPU threads, where a step's loops are short: with each pass of the parallel schedule in one
# launch (mls_mpm/persistent.py) the one serial launch measured faster (forward + backward) up to 1,600 particles on
# 64^2 (5,696 units, 1.18x), the parallel one from 4,000 on 64^2 (8,096 units, 1.22x; 1.6-1.8x from 8,000 particles;
# BENCHMARKS.md, "One launch a pass"). With a launch per step the crossover was 40,000 units.
SERIAL_BELOW_2D_TWO_THREADS = 7_000
# The same when those 2 threads are also the process's 2 CPUs, so that the worker threads are pinned one to each
# (mls_mpm/affinity.py, pins_workers below): the parallel schedule then measured faster (forward + backward) from
# 300 particles on 32^2 (1,324 units, 1.32x; the f64 thesis size, 2,269 units, 1.48x); at 100 particles on 32^2
# (1,124 units) the two were even (BENCHMARKS.md, "Worker threads pinned").
SERIAL_BELOW_2D_PINNED = 1_200
STENCIL = 4  # the cubic B-spline touches 4 nodes per axis (base = floor(x/dx) - 1)
DIMS = (2, 3)  # the dimensions the simulator runs in
GRAVITY = -9.8  # default gravity along y (axis 1), in 2D and 3D
MAX_THREADS = 1024  # CPU threads a simulation may ask for
MAX_PARTICLES_PER_CELL = 1024  # particles sampled per cell (per cell volume in 3D)


def default_threads() -> int:
    """CPU threads of `threads = 0`: the cores this process may run on (its affinity mask), else all cores."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def pins_workers(threads) -> bool:
    """Whether Taichi's `threads` CPU worker threads are to be pinned one to each CPU (mls_mpm/affinity.py): on
    Linux, with at least 2 threads, exactly as many as the CPUs this process may run on, where this process may set
    a thread's CPUs (a sandbox may forbid it: setting the calling thread's own mask to itself tells). A fact of the
    machine, not of its load: `auto` chooses the schedule by it (SimConfig.serial), so that a run's schedule, and
    with it its round-off, does not depend on whether the probe that singles out the workers succeeded."""
    if threads < 2 or not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        return False
    try:
        cpus = os.sched_getaffinity(0)
        if len(cpus) != threads:
            return False
        os.sched_setaffinity(0, cpus)  # no change; raises where setting masks is not allowed
        return True
    except OSError:
        return False


COMPILE_VARIABLE = "MLS_MPM_COMPILE"
COMPILE_MODES = ("optimized", "fast")


def compile_mode() -> str:
    """How Taichi compiles on the CPU, from the environment variable MLS_MPM_COMPILE: "fast" (the default: Taichi's
    own IR optimizations off; LLVM still optimizes) or "optimized" (on). Measured on 2 cores (BENCHMARKS.md,
    "Compile time"): with the one-launch kernels of the parallel schedule, "optimized" compiles a 2D simulator's
    forward and reverse kernels in about 14 s and a 3D one's in about 110-140 s, "fast" in about 5 s and 20 s, and a
    new shape (3D: of a new capacity, sizes.py) compiles afresh: a 30 s morph spent its whole budget compiling. "fast"
    runs 1.01-1.08x the optimized time per step (1.31x once, the f64 thesis-size backward) and gives the same
    results to the bit (tests/test_runtime.py). "optimized" pays for long runs of one scene whose kernels are
    cached. GPUs, and Taichi started for the Tape oracle, always get the optimizations
    (runtime.wants_optimized, TaichiRuntime.fits)."""
    mode = os.environ.get(COMPILE_VARIABLE) or "fast"
    if mode not in COMPILE_MODES:
        raise UserError(f"environment variable {COMPILE_VARIABLE} = {mode!r}: expected one of "
                        f"{', '.join(COMPILE_MODES)}")
    return mode


def min_n_grid(bound: int) -> int:
    """The smallest grid for walls `bound` cells wide: the default region, (bound + 2) cells inside each edge,
    must hold 2 cells, which also leaves room for the 4-node stencil inside the walls."""
    return 2 * (bound + 2) + 2


class CFLWarning(UserWarning):
    """dt exceeds the CFL limit of the material and grid."""


class ConfigError(UserError):
    """A setting has a value the simulator cannot use; the message names it and what is expected."""


@dataclass(frozen=True)
class SimConfig:
    """Settings of one simulation. Domain: the unit square (dim = 2) or cube (dim = 3); dx = 1 / n_grid.

    dim: 2 or 3; every kernel is one code path for both (vectors of size dim, a 4^dim stencil).
    n_grid: nodes per axis of the simulation grid (n_grid^dim nodes).
    steps: number of time steps N_t simulated by `Simulator.forward`.
    dt: time step (s).
    E, nu: Young's modulus and Poisson ratio of the fixed-corotated material (eq 9).
    density: rest density; particle rest volume V_p^0 = dx^dim / particles_per_cell, mass m_p = density V_p^0.
    gamma: drag coefficient of eq 16; gamma * dt must stay below 1.
    gravity: acceleration, dim numbers (default: -9.8 along y, (0, -9.8) or (0, -9.8, 0)); every node gains
        the impulse m_i dt g before eq 17's division.
    boundary: "slip" zeroes the velocity component into a wall, "sticky" the whole velocity,
        on nodes closer than `bound` cells to an edge.
    bound: width of the wall zone in cells.
    stride: control stride s; control k acts at step k*s, K = ceil(steps / s) controls.
    particles_per_cell: particles per cell area (2D) or volume (3D): sets V_p^0 and the sampling density
        (at most MAX_PARTICLES_PER_CELL).
    dtype: "f64" or "f32" for every field and kernel.
    arch: "cpu", or "gpu" (CUDA, else Vulkan), "cuda", "vulkan"; runtime.ensure refuses one that cannot start.
    threads: CPU threads, at most MAX_THREADS (0: the cores this process may run on, `default_threads()`);
        Taichi is re-initialised when it runs with another count (see runtime.TaichiRuntime).
    schedule: "parallel" runs parallel loops (on a CPU each pass in one launch whose threads meet at barriers,
        mls_mpm/persistent.py, or one launch per step when other work holds the CPUs; on a GPU one launch per
        step); "serial" runs all steps in one serial launch (faster for small scenes on a CPU); "auto" picks
        serial on a CPU with one thread or below SERIAL_BELOW particle-node units (2D on 2 threads:
        SERIAL_BELOW_2D_TWO_THREADS, or SERIAL_BELOW_2D_PINNED when they are to be pinned one to each of the
        process's 2 CPUs, pins_workers; see BENCHMARKS.md), else parallel. The choice depends on the settings,
        the particle count and the machine's CPUs, not on its load, so a run is bit-identical to itself.
    max_memory_gb: refuse a simulator whose preallocated fields would exceed this many GiB
        (0: 90% of the memory available when it is built).
    """

    dim: int = 2
    n_grid: int = 64
    steps: int = 200
    dt: float = 1e-4
    E: float = 1e3
    nu: float = 0.2
    density: float = 1.0
    gamma: float = 0.0
    gravity: tuple = None
    boundary: str = "slip"
    bound: int = 3
    stride: int = 10
    particles_per_cell: int = 4
    dtype: str = "f64"
    arch: str = "cpu"
    threads: int = 0
    schedule: str = "auto"
    max_memory_gb: float = 0.0

    def __post_init__(self):
        if isinstance(self.dim, bool) or self.dim not in DIMS:
            raise ConfigError(f"dim = {self.dim!r}: expected 2 or 3")
        if self.gravity is None:
            object.__setattr__(self, "gravity", (0.0, GRAVITY) + (0.0,) * (self.dim - 2))
        try:
            object.__setattr__(self, "gravity", tuple(float(g) for g in self.gravity))
        except (TypeError, ValueError):
            raise ConfigError(f"gravity = {self.gravity!r}: expected {self.dim} finite numbers") from None
        _check_int(self, "n_grid", min_n_grid(self.bound) if isinstance(self.bound, int) else min_n_grid(0))
        _check_int(self, "steps", 1)
        _check_int(self, "stride", 1)
        _check_int(self, "bound", 0)
        _check_int(self, "particles_per_cell", 1, MAX_PARTICLES_PER_CELL)
        _check_int(self, "threads", 0, MAX_THREADS)
        if isinstance(self.max_memory_gb, bool) or not isinstance(self.max_memory_gb, (int, float)) \
                or not self.max_memory_gb >= 0:
            raise ConfigError(f"max_memory_gb = {self.max_memory_gb!r}: expected a number >= 0 (0: automatic)")
        for name in ("dt", "E", "density"):
            _check_positive(self, name)
        if not (isinstance(self.nu, (int, float)) and 0.0 <= self.nu < 0.5):
            raise ConfigError(f"nu = {self.nu!r}: expected a Poisson ratio in [0, 0.5)")
        if not (isinstance(self.gamma, (int, float)) and self.gamma >= 0.0 and math.isfinite(self.gamma)):
            raise ConfigError(f"gamma = {self.gamma!r}: expected a drag coefficient >= 0")
        if self.gamma * self.dt >= 1.0:
            raise ConfigError(
                f"gamma * dt = {self.gamma * self.dt:g}: expected < 1, or the momentum factor (1 - dt gamma) "
                "of eq 16 flips sign; lower gamma or dt")
        if len(self.gravity) != self.dim or not all(math.isfinite(g) for g in self.gravity):
            raise ConfigError(f"gravity = {self.gravity!r}: expected {self.dim} finite numbers (one per axis, "
                              f"dim = {self.dim})")
        if self.stride > self.steps:
            raise ConfigError(f"stride = {self.stride}: expected at most steps = {self.steps}")
        if self.dt > self.cfl_dt:
            warnings.warn(f"dt = {self.dt:g} exceeds the CFL limit dx / sqrt((lambda + 2 mu) / density) = "
                          f"{self.cfl_dt:.4g}; the explicit update will likely blow up (scene files refuse it)",
                          CFLWarning, stacklevel=3)
        for name, allowed in (("boundary", BOUNDARIES), ("dtype", DTYPES), ("arch", ARCHS),
                                ("schedule", SCHEDULES)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"{name} = {getattr(self, name)!r}: expected one of {', '.join(allowed)}")

    # Derived quantities, named as in the thesis.
    @property
    def dx(self) -> float:
        return 1.0 / self.n_grid

    @property
    def inv_dx(self) -> float:
        return float(self.n_grid)

    @property
    def vol(self) -> float:
        """Particle rest volume V_p^0."""
        return self.dx ** self.dim / self.particles_per_cell

    @property
    def m_p(self) -> float:
        """Particle mass m_p."""
        return self.density * self.vol

    @property
    def mu(self) -> float:
        return self.E / (2.0 * (1.0 + self.nu))

    @property
    def lam(self) -> float:
        return self.E * self.nu / ((1.0 + self.nu) * (1.0 - 2.0 * self.nu))

    @property
    def n_controls(self) -> int:
        """K = ceil(N_t / s) control timesteps."""
        return -(-self.steps // self.stride)

    @property
    def wave_speed(self) -> float:
        """Dilatational wave speed sqrt((lambda + 2 mu) / rho)."""
        return math.sqrt((self.lam + 2.0 * self.mu) / self.density)

    @property
    def cfl_dt(self) -> float:
        """Largest stable explicit dt by the CFL condition dt <= dx / wave speed."""
        return self.dx / self.wave_speed

    def serial(self, n_particles, pinned=None) -> bool:
        """Whether stepping runs serially in one launch (see `schedule`). pinned: whether Taichi's worker threads
        are to be pinned; None: pins_workers, as the Simulator asks (a test may say either)."""
        if self.schedule != "auto":
            return self.schedule == "serial"
        if self.arch != "cpu":
            return False
        if self.cpu_threads == 1:  # one thread: the parallel schedule would only add its launches and private grid
            return True
        below = SERIAL_BELOW
        if self.dim == 2 and self.cpu_threads == 2:
            if pinned is None:
                pinned = pins_workers(2)
            below = SERIAL_BELOW_2D_PINNED if pinned else SERIAL_BELOW_2D_TWO_THREADS
        return n_particles + self.n_grid ** self.dim < below

    def lanes(self, n_particles, pinned=None) -> int:
        """Private scatter grids (one per CPU thread) of the parallel schedule; 0: atomics (GPU) or serial."""
        if self.arch != "cpu" or self.serial(n_particles, pinned):
            return 0
        return self.cpu_threads

    @property
    def cpu_threads(self) -> int:
        """The CPU threads Taichi runs with for this config: `threads`, or default_threads() for 0."""
        return self.threads or default_threads()

    def replace(self, **changes) -> "SimConfig":
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return SimConfig(**values)


def _check_int(cfg, name, least, most=None):
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, int) or value < least or (most is not None and value > most):
        expected = f"an integer >= {least}" if most is None else f"an integer in [{least}, {most}]"
        raise ConfigError(f"{name} = {value!r}: expected {expected}")


def _check_positive(cfg, name):
    value = getattr(cfg, name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (value > 0 and math.isfinite(value)):
        raise ConfigError(f"{name} = {value!r}: expected a finite number > 0")

