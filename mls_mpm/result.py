"""The result format of a run: result.npz (controls, initial states, final state, losses, settings) read back.

`run` writes it (run._finish) and `render` reads it; this module holds what both need, so neither imports the other.
load_result checks every array against the settings stored with it, so a damaged or crafted file is refused with
one line instead of failing deep inside rendering.
"""
import warnings
from pathlib import Path

from .checkpoint import CheckpointError, check_array, check_value, load_npz
from .config import SimConfig

STATE_KEYS = ("x", "v", "C", "F")


def state_shapes(dim=2) -> dict:
    """Per-particle shapes of the state arrays: x, v (dim), C, F (dim, dim)."""
    return {"x": (dim,), "v": (dim,), "C": (dim, dim), "F": (dim, dim)}


STATE_SHAPES = state_shapes(2)  # 2D, as before dim existed
RENDER_KEYS = ("mode", "size", "every")


def load_result(out_dir):
    """(meta, arrays) of a finished run's result.npz, with a one-line error when missing, corrupt or inconsistent."""
    path = Path(out_dir) / "result.npz"
    meta, arrays = load_npz(path, "result")
    needed = ("controls", "colors", "init_x", "init_v", "init_C", "init_F", "target_grid", "final_x")
    missing = [k for k in needed if k not in arrays] + [k for k in ("settings",) if k not in meta]
    if missing:
        raise CheckpointError(f"{path}: lacks {', '.join(missing)}; not a result of `mls-mpm run`")
    settings = check_value(path, "settings", meta["settings"], "table", "result")
    for section in ("sim", "control", "render", "scene", "loss"):
        check_value(path, f"settings.{section}", settings.get(section), "table", "result")
    for key in RENDER_KEYS:
        if key not in settings["render"]:
            check_value(path, f"settings.render.{key}", None, "int" if key != "mode" else "str", "result")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cfg = config_of(settings)
    except (TypeError, KeyError, ValueError) as e:
        raise CheckpointError(f"{path}: settings.sim are not a valid simulation ({e}); not a result of "
                              "`mls-mpm run`") from None
    d = cfg.dim
    controls = check_array(path, arrays, "controls", "f", (None, cfg.n_controls, None, d, d), "result")
    R, N = controls.shape[0], controls.shape[2]
    shapes = state_shapes(d)
    for k in STATE_KEYS:
        check_array(path, arrays, f"init_{k}", "f", (R, N, *shapes[k]), "result")
    check_array(path, arrays, "colors", "f", (N, 3), "result")
    check_array(path, arrays, "final_x", "f", (N, d), "result")
    grid = check_array(path, arrays, "target_grid", "f", (None,) * d, "result")
    check_array(path, arrays, "target_grid", "f", (grid.shape[0],) * d, "result")
    losses = check_array(path, arrays, "losses", "f", (None,), "result")
    lengths = check_array(path, arrays, "round_lengths", "i", (R,), "result")
    if int(lengths.sum()) != len(losses) or R == 0:
        raise CheckpointError(f"{path}: round_lengths {lengths.tolist()} do not add up to the {len(losses)} losses "
                              f"of {R} round(s); not a result of `mls-mpm run`")
    if "target_x" in arrays:
        check_array(path, arrays, "target_x", "f", (N, d), "result")
    if "target_points" in arrays or "target_colors" in arrays:
        M = len(check_array(path, arrays, "target_points", "f", (None, d), "result"))
        check_array(path, arrays, "target_colors", "f", (M, 3), "result")
    return meta, arrays


def config_of(settings, arch=None):
    """The SimConfig stored in a result's settings."""
    sim = dict(settings["sim"])
    sim["stride"] = settings["control"]["stride"]
    sim["gravity"] = tuple(sim["gravity"])
    if arch:
        sim["arch"] = arch
    return SimConfig(**sim)
