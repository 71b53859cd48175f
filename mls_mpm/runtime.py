"""Taichi initialisation for a SimConfig: called by the CLI and by Simulator, never at import.

One TaichiRuntime (RUNTIME) owns the process's Taichi settings (backend, float type, CPU threads) and counts
re-initialisations, so that a Simulator built before one refuses to run instead of touching freed fields.

`sim.arch` names what the user wants; Taichi silently falls back to the CPU when a backend is missing (and its
own `gpu` choice can crash on a headless machine while probing OpenGL), so each backend is tried here in turn,
only where its driver library exists, and a request that no backend here can serve is refused.
"""
from __future__ import annotations

import ctypes
import glob
import os
from dataclasses import dataclass

import taichi as ti
from taichi.lang import impl
from .blas import single_thread
from .config import compile_mode
from .errors import UserError
from .positions import short_positions
from .sources import read_sources_once

# what each sim.arch may run on, in the order tried
BACKENDS = {"cpu": ("cpu",), "gpu": ("cuda", "vulkan"), "cuda": ("cuda",), "vulkan": ("vulkan",)}
NEEDS = {"cuda": "an NVIDIA driver (libcuda.so)", "vulkan": "a Vulkan driver (libvulkan.so.1 and an ICD)"}


class ArchError(UserError):
    """The Taichi backend that sim.arch asks for is not available on this machine."""


def real(dtype: str):
    """The Taichi float type named by a config's dtype."""
    return ti.f64 if dtype == "f64" else ti.f32


def running_arch() -> str | None:
    """The backend Taichi runs on now: "cpu", "cuda", "vulkan", ...; None before ti.init."""
    if impl.get_runtime().prog is None:
        return None
    arch = impl.current_cfg().arch
    return "cpu" if arch in (ti.x64, ti.arm64) else arch.name


def _loadable(*names) -> bool:
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            pass
    return False


def _driver_present(backend: str) -> bool:
    """Cheap look for the backend's driver, so that Taichi is not started (and does not complain) in vain."""
    if backend == "cuda":
        return _loadable("libcuda.so", "libcuda.so.1")
    if backend == "vulkan":
        listed = os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES")
        icds = ([p for p in listed.split(os.pathsep) if os.path.isfile(p)] if listed else
                [p for d in ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d")
                 for p in glob.glob(os.path.join(d, "*.json"))])
        return bool(icds) and _loadable("libvulkan.so.1", "libvulkan.so")
    return True


def wants_optimized(backend: str) -> bool:
    """Whether a production runtime on this backend compiles with Taichi's IR optimizations
    (ti.init(advanced_optimization=...)): on a GPU always, on the CPU unless config.compile_mode() is "fast". A
    runtime started for the Tape always does (ensure): without them Taichi 1.7.4's 3D Tape kernels crash at launch
    and its float32 Tape gives a zero gradient."""
    return backend != "cpu" or compile_mode() == "optimized"


class StaleSimulatorError(RuntimeError):
    """A Simulator (or its fields) outlived the Taichi runtime it was built in."""


@dataclass(frozen=True)
class Settings:
    """What Taichi was initialised with: the backend it runs on, the float type and the CPU threads."""

    arch: str
    dtype: str
    threads: int
    scalarized: bool = False  # ti.init(force_scalarize_matrix=True): what the 3D Tape oracle needs (ensure)
    optimized: bool = True  # ti.init(advanced_optimization=...): off in compile_mode "fast"

    def __str__(self):
        return (f"{self.dtype} on {self.arch} with {self.threads} thread{'s' if self.threads != 1 else ''}"
                + (", matrices scalarized" if self.scalarized else "") + ("" if self.optimized else ", fast compile"))


class TaichiRuntime:
    """The one Taichi runtime of this process: its settings and a generation number.

    Re-initialising Taichi frees every field, so each re-initialisation bumps `generation`; an object built
    in an older generation (a Simulator records `generation` when it is built) refuses to run (`check`).
    """

    def __init__(self):
        self.generation = 0
        self.settings = None
        self._prog = None  # the Taichi program these settings describe (a ti.init elsewhere replaces it)
        self.pinned = {}  # {thread id: CPU} of the CPU worker threads ensure pinned (affinity.pin_workers)

    def current(self):
        """Settings of the running Taichi program, or None before ti.init (or after a ti.reset elsewhere)."""
        if impl.get_runtime().prog is None:
            return None
        if impl.get_runtime().prog is not self._prog:  # initialised outside ensure: read it, a new generation
            c = impl.current_cfg()
            self._started(Settings(running_arch(), "f64" if c.default_fp == ti.f64 else "f32",
                                   int(c.cpu_max_num_threads), bool(c.force_scalarize_matrix),
                                   bool(c.advanced_optimization)))
        return self.settings

    def _started(self, settings):
        self.generation += 1
        self.settings = settings
        self._prog = impl.get_runtime().prog
        self.pinned = {}

    def fits(self, cfg, tape=None) -> bool:
        """Whether the running Taichi serves cfg (its dtype, arch and CPU threads) and `tape` (module ensure)."""
        cur = self.current()
        if cur is None:
            return False
        if tape is None:  # a Simulator: matrices and optimizations either way
            matrices_fit = optimization_fits = True
        elif tape:
            matrices_fit = cur.scalarized or not needs_scalarized(cfg, tape)
            # Taichi 1.7.4's Tape kernels compiled without its IR optimizations gave a zero gradient in float32
            # (found by trial; in float64 they match the manual kernels, which the suite checks)
            optimization_fits = cur.optimized or cfg.dtype == "f64"
        else:
            matrices_fit = not cur.scalarized
            optimization_fits = cur.optimized == wants_optimized(cur.arch)
        return (cur.dtype == cfg.dtype and cur.arch in BACKENDS[cfg.arch]
                and (cur.arch != "cpu" or cur.threads == cfg.cpu_threads) and not impl.current_cfg().fast_math
                and matrices_fit and optimization_fits)

    def ensure(self, cfg, tape=None) -> int:
        """Initialise Taichi for cfg's arch, dtype and CPU threads, and for `tape` (see the module function
        ensure), re-initialising when any differs; return the generation. Raises ArchError when no backend that
        cfg.arch allows can start here."""
        single_thread()  # numpy's BLAS off the simulator's CPUs (blas.py), however Taichi was started
        short_positions()  # Taichi's front end without a wrapped caret line per node (positions.py)
        read_sources_once()  # ... and reading each ti.func's source once, not at every call site (sources.py)
        if self.fits(cfg, tape):
            return self.generation
        if impl.get_runtime().prog is not None:
            ti.reset()
        allowed = BACKENDS[cfg.arch]
        threads = cfg.cpu_threads
        # unrolling_limit=0: the 3D stencil's 4^3 = 64 nodes are unrolled on purpose (ti.static), which Taichi
        # would otherwise warn of at every compile
        scalarized = needs_scalarized(cfg, bool(tape))
        # cpu_block_dim_adaptive (Taichi's default, set here because state.LANE_TASK relies on it): how a CPU
        # range-for is cut into tasks, which gives each thread one lane of the scatter loops
        kwargs = dict(default_fp=real(cfg.dtype), fast_math=False, offline_cache=True, cpu_max_num_threads=threads,
                      cpu_block_dim_adaptive=True, unrolling_limit=0, force_scalarize_matrix=scalarized)
        for backend in allowed:
            if not _driver_present(backend):
                continue
            optimized = bool(tape) or wants_optimized(backend)  # the Tape: always (wants_optimized)
            # ERROR: no fallback warning
            ti.init(arch=getattr(ti, backend), log_level=ti.ERROR, advanced_optimization=optimized, **kwargs)
            ti.set_logging_level(ti.WARN)
            if running_arch() == backend:
                self._started(Settings(backend, cfg.dtype, threads, scalarized, optimized))
                if backend == "cpu":
                    from .affinity import pin_workers  # here: affinity imports state, which imports this module

                    self.pinned = pin_workers(threads)
                return self.generation
            ti.reset()  # Taichi fell back to the CPU
        self.settings = None
        raise ArchError(f"sim.arch = {cfg.arch}: no {' or '.join(allowed)} device that Taichi can use on this "
                        f"machine ({'; '.join(f'{b} needs {NEEDS[b]}' for b in allowed)}); use sim.arch = cpu")

    def check(self, generation, built_for, what="this Simulator"):
        """Raise StaleSimulatorError when Taichi was re-initialised after generation `generation`."""
        self.current()
        if generation != self.generation or impl.get_runtime().prog is None:
            now = (f"re-initialised for {self.settings}" if impl.get_runtime().prog is not None else "reset")
            raise StaleSimulatorError(f"{what} was built for {built_for}; Taichi has since been {now}, which freed "
                                      "its fields; build a new Simulator")


RUNTIME = TaichiRuntime()


def needs_scalarized(cfg, tape) -> bool:
    """Whether Taichi must scalarize matrices (ti.init(force_scalarize_matrix=True)) for cfg: for the Tape oracle in
    3D, where the stencil's first axis is a runtime loop; Taichi 1.7.4's reverse of that loop came out right only
    scalarized (found by trial, with kernels.carry and kernels.axis0). Production runs never are: the manual
    kernels compile slower scalarized."""
    return bool(tape) and cfg.dim == 3


def ensure(cfg, tape=None) -> int:
    """Initialise Taichi for cfg (RUNTIME.ensure); return the runtime's generation.

    tape=True: fit for ti.ad.Tape on cfg's kernels (in 3D, matrices scalarized: needs_scalarized; in 2D either;
    Taichi's IR optimizations on when Taichi starts here, and kept on in float32: RUNTIME.fits); False: not
    scalarized, optimized as compile_mode says (the production setting); None (Simulator, the CLI): either, so a
    Simulator can be built where the Tape oracle runs. Re-initialising frees every field: simulators made under
    other settings refuse to run afterwards.
    """
    return RUNTIME.ensure(cfg, tape)
