"""Differentiable MLS-MPM in 2D and 3D for shape-morphing animation (M. Xu, 2020), with hand-written reverse kernels.

Importing the package imports nothing else: each name below, and each submodule (`mls_mpm.runtime`, ...), is
imported on first use (PEP 562), so the command line starts without loading Taichi.
"""
import importlib
import importlib.util

_EXPORTS = {  # name -> the submodule that defines it
    "SimConfig": "config", "ConfigError": "config",
    "Simulator": "simulator", "SimulationError": "errors",
    "PositionLoss": "losses", "MassLoss": "losses", "ColorLoss": "losses", "OTLoss": "losses", "LossError": "losses",
}

__all__ = list(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
