"""Render a finished run from its result.npz: re-simulate the stored controls, one frame at a time.

Writes frames/frame_NNNNN.png every `every` steps of every round in sequence, animation.gif, animation.mp4,
sheet.png (initial | middle | final | target) and loss.png. A 3D run (sim.dim = 3) also writes, for the same
frames, particles/frame_NNNNN.ply and meshes/frame_NNNNN.ply (export3d.py), and its frames are the headless
preview of render3d.py (modes surface | volume | particles; a scene's 2D mode mass or color means surface, a
colour scene showing its colours). Used by `mls-mpm run` and `mls-mpm render`, so both produce the same bytes.

Nothing is allocated or written before the options are checked, the folder's summary.json is found to be of
the same run as result.npz, and the renderer is known to fit in memory. The frames go to frames.new/ (and the
3D sequences to particles.new/, meshes.new/) and replace frames/ only when all are written; a failure, or
should_stop turning true before a frame, deletes the .new folders and keeps the old ones. The GIF, the video,
the sheet and the loss plot are built after the swap, each atomically.
"""
import json
import re
import time
from pathlib import Path

import numpy as np
from PIL import Image

from . import memory, runtime
from .errors import Interrupted, UserError
from .export3d import MESHES_DIR, MODES_3D, PARTICLES_DIR, PLY_NAME, PLY_RE, surface, write_mesh, write_particles
from .field3d import frame_field, mass_field
from .frames import (FRAME_RE, FRAMES_DIR, NEW_DIR, FrameWriter, discard_new, frame_paths, loss_plot, on_white,
                     recover, remove_stale_temps, save_png, sheet, swap_in, write_gif)
from .problem import rest_node_mass
from .render import BACKGROUNDS, Renderer, estimate_bytes
from .render3d import Preview3D, estimate_bytes_3d
from .result import STATE_KEYS, config_of, load_result
from .scene import RENDER_MODES, RENDER_SIZE_MAX, RENDER_SIZE_MIN
from .simulator import Simulator
from .video import write_mp4

OUTPUTS_RE = re.compile(r"^(animation\.gif|animation\.mp4|sheet\.png|loss\.png)$")  # the files built from the frames
SEQUENCES = {FRAMES_DIR: FRAME_RE, PARTICLES_DIR: PLY_RE, MESHES_DIR: PLY_RE}  # folders a render swaps in
MODE_3D_OF = {"mass": "surface", "color": "surface"}  # a scene's 2D render.mode (its default) in a 3D run


class RenderError(UserError):
    """A render option, or the run folder to render, cannot be used."""


def render_run(out_dir, mode=None, size=None, every=None, arch=None, emit=print, should_stop=None, sim=None):
    """Render the run in out_dir; mode/size/every default (None) to the scene's [render] settings.

    should_stop: a callable polled before each frame; when it turns true, rendering stops by raising
    errors.Interrupted, the old frames kept. sim: the Simulator that made the run (mls-mpm run's own), used for the
    re-simulation where it serves the result's settings and particle count (Simulator.serves): Taichi then does
    not build its kernels a second time (about 3 s of a 3D run's rendering on 2 cores, BENCHMARKS.md) and no
    second set of fields is allocated; the frames are the same bytes either way. Returns the paths of the frames
    written.
    """
    out = Path(out_dir)
    meta, arrays = load_result(out)
    settings = meta["settings"]
    _check_summary(out, settings)
    rs = settings["render"]
    where = f"in {out / 'result.npz'}"
    cfg = config_of(settings, arch)
    dim = cfg.dim
    stored = dict(rs, mode=MODE_3D_OF.get(rs["mode"], rs["mode"]) if dim == 3 else rs["mode"])
    size_named = f"--size {size}" if size is not None else f"render.size = {rs['size']} {where}"
    mode, size, every = (_option(name, value, stored[name], where, MODES_3D if dim == 3 else RENDER_MODES)
                         for name, value in (("mode", mode), ("size", size), ("every", every)))
    background = rs.get("background", "white")
    if background not in BACKGROUNDS:
        raise RenderError(f"render.background = {background!r} {where}: expected one of {', '.join(BACKGROUNDS)}")
    controls = arrays["controls"]
    N = controls.shape[2]
    outline = arrays["target_grid"] if rs.get("outline", False) else None
    if sim is not None and not sim.serves(cfg, N):
        sim = None  # a simulator of other settings: _states builds one
    _check_memory(cfg, N, size, mode, None if outline is None else len(outline), size_named,
                  new_simulator=sim is None)
    emit(f"rendering scene {settings['scene']['name']} from {out / 'result.npz'}")
    sequences = list(SEQUENCES) if dim == 3 else [FRAMES_DIR]
    timing = {}
    try:
        for folder in sequences:
            recover(out, folder, SEQUENCES[folder])
        remove_stale_temps(out, OUTPUTS_RE)
        runtime.ensure(cfg)  # the Renderer allocates fields before any Simulator starts Taichi
        if dim == 2:
            renderer = Renderer(cfg.n_grid, N, size=size, rest_node_mass=rest_node_mass(cfg, cfg.n_grid),
                                mode=mode, body_outline=outline is not None, background=background)
            writer = FrameWriter(out, folder=NEW_DIR)
            for state in _states(cfg, meta, arrays, every, sim):
                if should_stop is not None and should_stop():
                    raise Interrupted("rendering interrupted; the old frames are kept")
                writer.write(renderer.render(state["x"], cfg.m_p, colors=arrays["colors"], F=state["F"],
                                             target_x=arrays.get("target_x"), target_outline=outline))
        else:
            renderer = Preview3D(cfg.n_grid, size, mode, colored=_colored(settings),
                                 spacing=cfg.dx / cfg.particles_per_cell ** (1 / 3))
            _render_3d(out, renderer, cfg, meta, arrays, every, outline, should_stop, timing, sim)
        frames_dir = [swap_in(out, folder) for folder in sequences][0]
    except OSError as e:
        for folder in sequences:
            discard_new(out, folder)
        raise RenderError(f"{out}: cannot write the frames ({e.strerror or e})") from None
    except BaseException:
        for folder in sequences:
            discard_new(out, folder)
        raise
    paths = frame_paths(frames_dir)
    emit(f"wrote {len(paths)} frames to {frames_dir}" + (f" and as many to {out / PARTICLES_DIR}, "
                                                           f"{out / MESHES_DIR}" if dim == 3 else ""))
    if timing:
        emit("per frame: " + ", ".join(f"{k} {1e3 * v / len(paths):.1f} ms" for k, v in timing.items()))
    if rs.get("gif", True):
        write_gif(frames_dir, out / "animation.gif")
    else:
        (out / "animation.gif").unlink(missing_ok=True)  # a GIF of other frames
    if rs.get("mp4", True):
        write_mp4(frames_dir, out / "animation.mp4")
    else:
        (out / "animation.mp4").unlink(missing_ok=True)  # a video of other frames
    panels = []
    for i in (0, len(paths) // 2, len(paths) - 1):
        with Image.open(paths[i]) as im:
            panels.append(np.asarray(on_white(im)))
    target = (_target_panel(renderer, arrays, cfg, settings) if dim == 2 else
              _target_panel_3d(renderer, arrays, cfg, settings))
    panels.append(np.asarray(on_white(Image.fromarray(target))))  # a transparent frame's target too
    save_png(sheet(panels, ["initial", "middle", "final", "target"]), out / "sheet.png")
    loss_plot(arrays["losses"], out / "loss.png")
    return paths


def _render_3d(out, preview, cfg, meta, arrays, every, outline, should_stop, timing, sim):
    """Write each 3D frame's preview, particles and mesh into the .new folders; timing: seconds spent per part
    (the re-simulation, the field, each output), summed over the frames; sim: as render_run's."""
    frames = FrameWriter(out, folder=NEW_DIR)
    particles = FrameWriter(out, folder=f"{PARTICLES_DIR}.new", name=PLY_NAME, pattern=PLY_RE, save=write_particles)
    meshes = FrameWriter(out, folder=f"{MESHES_DIR}.new", name=PLY_NAME, pattern=PLY_RE, save=write_mesh)
    colors = arrays["colors"]
    target = None if outline is None else outline / (cfg.density / len(outline) ** 3)
    for k in ("simulation", "field", "preview", "particles", "mesh"):
        timing[k] = 0.0

    def timed(part, fn, *args):
        t0 = time.perf_counter()
        value = fn(*args)
        timing[part] += time.perf_counter() - t0
        return value

    states = _states(cfg, meta, arrays, every, sim)
    while (state := timed("simulation", next, states, None)) is not None:
        if should_stop is not None and should_stop():
            raise Interrupted("rendering interrupted; the old frames are kept")
        x = state["x"]
        field, density = timed("field", frame_field, x, cfg.m_p, cfg.n_grid, cfg.density, colors)
        timed("preview", lambda: frames.write(preview.render(field, x, colors, target)))
        timed("particles", lambda: particles.write((x, colors, density)))
        timed("mesh", lambda: meshes.write(surface(field)))


def _colored(settings):
    """Whether a 3D preview shows the particles' colours (a colour scene) rather than the mass colormap."""
    return settings["loss"].get("kind") == "color" or settings["render"].get("mode") == "color"


def _option(name, value, stored, where, modes=RENDER_MODES):
    """A render option checked: value, or the scene's stored value when value is None (0 is refused); modes:
    the modes of the run's dimension."""
    what = f"--{name} {value}" if value is not None else f"render.{name} = {stored} {where}"
    value = stored if value is None else value
    integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
    if name == "mode" and value not in modes:
        raise RenderError(f"{what}: expected one of {', '.join(modes)}" +
                          (" (a 3D run)" if modes == MODES_3D else ""))
    if name == "size" and not (integer and RENDER_SIZE_MIN <= value <= RENDER_SIZE_MAX):
        raise RenderError(f"{what}: expected an integer number of pixels between {RENDER_SIZE_MIN} and "
                          f"{RENDER_SIZE_MAX}")
    if name == "every" and not (integer and value >= 1):
        raise RenderError(f"{what}: expected an integer number of steps >= 1")
    return value if name == "mode" else int(value)


def _check_memory(cfg, n_particles, size, mode, target_res, what, new_simulator=True):
    """Refuse, before anything is allocated, a renderer that would not fit beside the re-simulation: within
    sim.max_memory_gb when set, else 90% of the memory free now (as memory.check_memory for the simulation).
    new_simulator: whether the re-simulation allocates a Simulator; else it reuses the run's, whose fields count
    against sim.max_memory_gb but are no longer in the free memory."""
    word = 8 if cfg.dtype == "f64" else 4
    need = (estimate_bytes(cfg.n_grid, n_particles, size, mode, word, target_res) if cfg.dim == 2 else
            estimate_bytes_3d(cfg.n_grid, n_particles, size, mode, word, target_res))
    sim = memory.estimate_bytes(cfg, n_particles) if new_simulator or cfg.max_memory_gb else 0
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


def _states(cfg, meta, arrays, every, sim=None):
    """The states of the frames in order: every `every` steps of each round (a round's first frame is the
    last of the one before), or, for the positions method, the sampled shape and the optimized positions. sim: the
    Simulator to re-simulate with (render_run has found that it serves), or None: one is built."""
    if meta.get("method") == "positions":  # no animation
        first = {k: arrays[f"init_{k}"][0] for k in STATE_KEYS}
        yield first
        yield {**first, "x": arrays["final_x"]}
        return
    controls = arrays["controls"]
    if sim is None:
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
        return renderer.render(arrays["target_points"], _target_mass(arrays, cfg, settings),
                               colors=arrays["target_colors"])
    return renderer.render(arrays["target_x"], cfg.m_p, colors=arrays["colors"])


def _target_mass(arrays, cfg, settings):
    """The mass of a sampled target particle: the body's, or spread over the target's count ("match")."""
    match = settings["scene"]["target_density"] == "match"
    return cfg.m_p * (len(arrays["final_x"]) / len(arrays["target_points"]) if match else 1)


def _target_panel_3d(preview, arrays, cfg, settings):
    """The 3D target as the preview shows the body: its sampled particles (and colours) when the result holds
    them; else (position targets) the particles' targets."""
    if "target_points" in arrays:
        pts, m_t, colors = arrays["target_points"], _target_mass(arrays, cfg, settings), arrays["target_colors"]
    else:
        pts, m_t, colors = arrays["target_x"], cfg.m_p, arrays["colors"]
    return preview.render(mass_field(pts, m_t, cfg.n_grid, cfg.density, colors), pts, colors)
