"""The result format of a run: result.npz (controls, initial states, final state, losses, settings) read back.

`run` writes it (run._finish) and `render` reads it; this module holds what both need, so neither imports the other.
"""
from pathlib import Path

from .checkpoint import CheckpointError, load_npz
from .config import SimConfig

STATE_KEYS = ("x", "v", "C", "F")


def load_result(out_dir):
    """(meta, arrays) of a finished run's result.npz, with a one-line error when missing or corrupt."""
    meta, arrays = load_npz(Path(out_dir) / "result.npz", "result")
    needed = ("controls", "colors", "init_x", "init_v", "init_C", "init_F", "target_grid", "final_x")
    missing = [k for k in needed if k not in arrays] + [k for k in ("settings",) if k not in meta]
    if missing:
        raise CheckpointError(f"{Path(out_dir) / 'result.npz'}: lacks {', '.join(missing)}; not a result of "
                              "`mls-mpm run`")
    return meta, arrays


def config_of(settings, arch=None):
    """The SimConfig stored in a result's settings."""
    sim = dict(settings["sim"])
    sim["stride"] = settings["control"]["stride"]
    sim["gravity"] = tuple(sim["gravity"])
    if arch:
        sim["arch"] = arch
    return SimConfig(**sim)
