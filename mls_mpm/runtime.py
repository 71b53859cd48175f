"""Taichi initialisation for a SimConfig: called by the CLI and by Simulator, never at import."""
from __future__ import annotations

import taichi as ti
from taichi.lang import impl

_ARCH = {"cpu": "cpu", "gpu": "gpu", "cuda": "cuda", "vulkan": "vulkan"}


def real(dtype: str):
    """The Taichi float type named by a config's dtype."""
    return ti.f64 if dtype == "f64" else ti.f32


def ensure(cfg) -> None:
    """Initialise Taichi for cfg's arch and dtype, re-initialising when they differ.

    Re-initialising frees every field, so simulators made under other settings become unusable.
    """
    want_fp = real(cfg.dtype)
    if impl.get_runtime().prog is not None:
        current = impl.current_cfg()
        same_arch = (cfg.arch == "cpu") == (current.arch in (ti.x64, ti.arm64))
        if current.default_fp == want_fp and same_arch and not current.fast_math:
            return
        ti.reset()
    kwargs = dict(default_fp=want_fp, fast_math=False, offline_cache=True, log_level=ti.WARN)
    if cfg.threads:
        kwargs["cpu_max_num_threads"] = cfg.threads
    ti.init(arch=getattr(ti, _ARCH[cfg.arch]), **kwargs)
