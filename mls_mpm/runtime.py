"""Taichi initialisation for a SimConfig: called by the CLI and by Simulator, never at import.

`sim.arch` names what the user wants; Taichi silently falls back to the CPU when a backend is missing (and
its own `gpu` choice can crash on a headless machine while probing OpenGL), so each backend is tried here in
turn, only where its driver library exists, and a request that no backend here can serve is refused.
"""
from __future__ import annotations

import ctypes
import glob
import os

import taichi as ti
from taichi.lang import impl
from .errors import UserError

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


def ensure(cfg) -> None:
    """Initialise Taichi for cfg's arch and dtype, re-initialising when they differ.

    Re-initialising frees every field, so simulators made under other settings become unusable.
    Raises ArchError when no backend that cfg.arch allows can start here.
    """
    want_fp = real(cfg.dtype)
    allowed = BACKENDS[cfg.arch]
    if impl.get_runtime().prog is not None:
        current = impl.current_cfg()
        if current.default_fp == want_fp and running_arch() in allowed and not current.fast_math:
            return
        ti.reset()
    kwargs = dict(default_fp=want_fp, fast_math=False, offline_cache=True)
    if cfg.threads:
        kwargs["cpu_max_num_threads"] = cfg.threads
    for backend in allowed:
        if not _driver_present(backend):
            continue
        ti.init(arch=getattr(ti, backend), log_level=ti.ERROR, **kwargs)  # ERROR: no fallback warning
        ti.set_logging_level(ti.WARN)
        if running_arch() == backend:
            return
        ti.reset()  # Taichi fell back to the CPU
    raise ArchError(f"sim.arch = {cfg.arch}: no {' or '.join(allowed)} device that Taichi can use on this "
                    f"machine ({'; '.join(f'{b} needs {NEEDS[b]}' for b in allowed)}); use sim.arch = cpu")
