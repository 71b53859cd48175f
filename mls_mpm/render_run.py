"""Render a finished run from its result.npz: re-simulate the stored controls, one frame at a time.

Writes frames/frame_NNNNN.png every `every` steps of every round in sequence, animation.gif, sheet.png
(initial | middle | final | target) and loss.png. Used by `mls-mpm run` and `mls-mpm render`, so both
produce the same bytes.

Nothing is allocated or written before the options are checked, the folder's summary.json is found to be of
the same run as result.npz, and the renderer is known to fit in memory. The frames go to frames.new/ and replace
frames/ only when all are written; a failure, or should_stop turning true before a frame, deletes frames.new/
and keeps the old frames. The GIF, the sheet and the loss plot are built after the swap, each atomically.
"""
import json
import re
from pathlib import Path

import numpy as np
from PIL import Image

from . import memory, runtime
from .errors import Interrupted, UserError
from .frames import (NEW_DIR, FrameWriter, discard_new, frame_paths, loss_plot, recover, remove_stale_temps,
                     save_png, sheet, swap_in, write_gif)
from .problem import rest_node_mass
from .render import Renderer, estimate_bytes
from .result import STATE_KEYS, config_of, load_result
from .scene import RENDER_MODES, RENDER_SIZE_MAX, RENDER_SIZE_MIN
from .simulator import Simulator

OUTPUTS_RE = re.compile(r"^(animation\.gif|sheet\.png|loss\.png)$")  # the files built from the frames


class RenderError(UserError):
    """A render option, or the run folder to render, cannot be used."""


def render_run(out_dir, mode=None, size=None, every=None, arch=None, emit=print, should_stop=None):
    """Render the run in out_dir; mode/size/every default (None) to the scene's [render] settings.

    should_stop: a callable polled before each frame; when it turns true, rendering stops by raising
    errors.Interrupted, the old frames kept. Returns the paths of the frames written.
    """
    out = Path(out_dir)
    meta, arrays = load_result(out)
    settings = meta["settings"]
    _check_summary(out, settings)
    rs = settings["render"]
    where = f"in {out / 'result.npz'}"
    size_named = f"--size {size}" if size is not None else f"render.size = {rs['size']} {where}"
    mode, size, every = (_option(name, value, rs[name], where) for name, value in
                         (("mode", mode), ("size", size), ("every", every)))
    cfg = config_of(settings, arch)
    controls = arrays["controls"]
    N = controls.shape[2]
    outline = arrays["target_grid"] if rs.get("outline", False) else None
    _check_memory(cfg, N, size, mode, None if outline is None else len(outline), size_named)
    emit(f"rendering scene {settings['scene']['name']} from {out / 'result.npz'}")
    try:
        recover(out)
        remove_stale_temps(out, OUTPUTS_RE)
        runtime.ensure(cfg)  # the Renderer allocates fields before any Simulator starts Taichi
        renderer = Renderer(cfg.n_grid, N, size=size, rest_node_mass=rest_node_mass(cfg, cfg.n_grid), mode=mode,
                            body_outline=outline is not None)
        writer = FrameWriter(out, folder=NEW_DIR)
        for state in _states(cfg, meta, arrays, every):
            if should_stop is not None and should_stop():
                raise Interrupted("rendering interrupted; the old frames are kept")
            writer.write(renderer.render(state["x"], cfg.m_p, colors=arrays["colors"], F=state["F"],
                                         target_x=arrays.get("target_x"), target_outline=outline))
        frames_dir = swap_in(out)
    except OSError as e:
        discard_new(out)
        raise RenderError(f"{out}: cannot write the frames ({e.strerror or e})") from None
    except BaseException:
        discard_new(out)
        raise
    paths = frame_paths(frames_dir)
    emit(f"wrote {len(paths)} frames to {frames_dir}")
    if rs.get("gif", True):
        write_gif(frames_dir, out / "animation.gif")
    else:
        (out / "animation.gif").unlink(missing_ok=True)  # a GIF of other frames
    panels = [np.asarray(Image.open(paths[i]).convert("RGB")) for i in (0, len(paths) // 2, len(paths) - 1)]
    panels.append(_target_panel(renderer, arrays, cfg, settings))
    save_png(sheet(panels, ["initial", "middle", "final", "target"]), out / "sheet.png")
    loss_plot(arrays["losses"], out / "loss.png")
    return paths


def _option(name, value, stored, where):
    """A render option checked: value, or the scene's stored value when value is None (0 is refused)."""
    what = f"--{name} {value}" if value is not None else f"render.{name} = {stored} {where}"
    value = stored if value is None else value
    integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if name == "mode" and value not in RENDER_MODES:
        raise RenderError(f"{what}: expected one of {', '.join(RENDER_MODES)}")
    if name == "size" and not (integer and RENDER_SIZE_MIN <= value <= RENDER_SIZE_MAX):
        raise RenderError(f"{what}: expected an integer number of pixels between {RENDER_SIZE_MIN} and "
                          f"{RENDER_SIZE_MAX}")
    if name == "every" and not (integer and value >= 1):
        raise RenderError(f"{what}: expected an integer number of steps >= 1")
    return value if name == "mode" else int(value)


def _check_memory(cfg, n_particles, size, mode, target_res, what):
    """Refuse, before anything is allocated, a renderer that would not fit beside the re-simulation: within
    sim.max_memory_gb when set, else 90% of the memory free now (as memory.check_memory for the simulation)."""
    need = estimate_bytes(cfg.n_grid, n_particles, size, mode, 8 if cfg.dtype == "f64" else 4, target_res)
    sim = memory.estimate_bytes(cfg, n_particles)
    limit, of = memory.limit(cfg)
    if limit is not None and need + sim > limit:
        raise RenderError(f"{what}: the renderer needs about {need / 2 ** 30:.2f} GiB beside the simulation's "
                          f"{sim / 2 ** 30:.2f} GiB, above the limit of {limit / 2 ** 30:.2f} GiB ({of}); "
                          "render a smaller size")


def _check_summary(out, settings):
    """Refuse a folder whose summary.json (when there is one) is of another scene or settings than result.npz."""
    path = out / "summary.json"
    if not path.exists():
        return
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise RenderError(f"{path}: not readable ({type(e).__name__}); delete it or re-run the scene") from None
    if not isinstance(summary, dict):
        raise RenderError(f"{path}: not the summary of a run; delete it or re-run the scene")
    mixed = "the folder mixes two runs: re-run the scene into it, or delete summary.json to render result.npz"
    name = settings["scene"]["name"]
    if summary.get("scene") != name:
        raise RenderError(f"{out}: summary.json is of scene {summary.get('scene')}, result.npz of scene {name}; "
                          f"{mixed}")
    differ = _difference(summary.get("settings"), settings)
    if differ:
        key, a, b = differ
        raise RenderError(f"{out}: summary.json and result.npz differ in {key} ({a} vs {b}); {mixed}")


def _difference(a, b, key=""):
    """(dotted key, value in a, value in b) of the first place where two JSON values differ, or None."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            found = _difference(a.get(k), b.get(k), f"{key}.{k}" if key else k)
            if found:
                return found
        return None
    a, b = json.dumps(a, sort_keys=True), json.dumps(b, sort_keys=True)  # NaN equals NaN here
    return None if a == b else (key or "settings", a, b)


def _states(cfg, meta, arrays, every):
    """The states of the frames in order: every `every` steps of each round (a round's first frame is the
    last of the one before), or, for the positions method, the sampled shape and the optimized positions."""
    if meta.get("method") == "positions":  # no animation
        first = {k: arrays[f"init_{k}"][0] for k in STATE_KEYS}
        yield first
        yield {**first, "x": arrays["final_x"]}
        return
    controls = arrays["controls"]
    sim = Simulator(cfg, arrays["init_x"][0])
    steps = list(range(0, cfg.steps + 1, every))
    if steps[-1] != cfg.steps:
        steps.append(cfg.steps)
    for r in range(len(controls)):
        sim.set_initial(*(arrays[f"init_{k}"][r] for k in STATE_KEYS))
        sim.forward(controls[r])
        for n in steps[(1 if r else 0):]:
            yield sim.state(n)


def _target_panel(renderer, arrays, cfg, settings):
    """The target as the renderer shows the body: its sampled particles, or the position-loss targets."""
    if "target_points" in arrays:
        pts = arrays["target_points"]
        m_t = cfg.m_p * (len(arrays["final_x"]) / len(pts) if settings["scene"]["target_density"] == "match" else 1)
        return renderer.render(pts, m_t, colors=arrays["target_colors"])
    return renderer.render(arrays["target_x"], cfg.m_p, colors=arrays["colors"])
