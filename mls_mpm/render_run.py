"""Render a finished run from its result.npz: re-simulate the stored controls, one frame at a time.

Writes frames/frame_NNNNN.png every `every` steps of every round in sequence, animation.gif, sheet.png
(initial | middle | final | target) and loss.png. Used by `mls-mpm run` and `mls-mpm render`, so both
produce the same bytes.
"""
from pathlib import Path

import numpy as np
from PIL import Image

from .frames import FrameWriter, frame_paths, loss_plot, save_png, sheet, write_gif
from . import runtime
from .render import Renderer
from .result import STATE_KEYS, config_of, load_result
from .simulator import Simulator

MODES = ("mass", "color", "particles")


def render_run(out_dir, mode=None, size=None, every=None, arch=None, emit=print, should_stop=None):
    """Render the run in out_dir; mode/size/every default to the scene's [render] settings.

    should_stop: a callable polled between frames; when it turns true, rendering stops by raising
    errors.Interrupted.
    """
    out = Path(out_dir)
    meta, arrays = load_result(out)
    settings = meta["settings"]
    rs = settings["render"]
    mode = mode or rs["mode"]
    size = int(size or rs["size"])
    every = int(every or rs["every"])
    cfg = config_of(settings, arch)
    runtime.ensure(cfg)  # the Renderer allocates fields before any Simulator starts Taichi
    controls = arrays["controls"]
    n_rounds, N = controls.shape[0], controls.shape[2]
    rest = cfg.density * cfg.dx ** 2
    renderer = Renderer(cfg.n_grid, N, size=size, rest_node_mass=rest, mode=mode,
                        body_outline=bool(rs.get("outline", False)))
    colors = arrays["colors"]
    target_x = arrays.get("target_x")
    outline = arrays["target_grid"] if rs.get("outline", False) else None

    def draw(state):
        return renderer.render(state["x"], cfg.m_p, colors=colors, F=state["F"], target_x=target_x,
                               target_outline=outline)

    writer = FrameWriter(out)
    if meta.get("method") == "positions":  # no animation: the sampled shape and the optimized positions
        first = {k: arrays[f"init_{k}"][0] for k in STATE_KEYS}
        writer.write(draw(first))
        writer.write(draw({**first, "x": arrays["final_x"]}))
    else:
        sim = Simulator(cfg, arrays["init_x"][0])
        steps = list(range(0, cfg.steps + 1, every))
        if steps[-1] != cfg.steps:
            steps.append(cfg.steps)
        for r in range(n_rounds):
            sim.set_initial(*(arrays[f"init_{k}"][r] for k in STATE_KEYS))
            sim.forward(controls[r])
            for n in steps[(1 if r else 0):]:  # a round's first frame is the last frame of the one before
                writer.write(draw(sim.state(n)))
    paths = frame_paths(writer.frames_dir)
    emit(f"wrote {len(paths)} frames to {writer.frames_dir}")
    if rs.get("gif", True):
        write_gif(writer.frames_dir, out / "animation.gif")
    panels = [np.asarray(Image.open(paths[i]).convert("RGB")) for i in (0, len(paths) // 2, len(paths) - 1)]
    panels.append(_target_panel(renderer, arrays, cfg, settings))
    save_png(sheet(panels, ["initial", "middle", "final", "target"]), out / "sheet.png")
    loss_plot(arrays["losses"], out / "loss.png")
    return paths


def _target_panel(renderer, arrays, cfg, settings):
    """The target as the renderer shows the body: its sampled particles, or the position-loss targets."""
    if "target_points" in arrays:
        pts = arrays["target_points"]
        m_t = cfg.m_p * (len(arrays["final_x"]) / len(pts) if settings["scene"]["target_density"] == "match" else 1)
        return renderer.render(pts, m_t, colors=arrays["target_colors"])
    return renderer.render(arrays["target_x"], cfg.m_p, colors=arrays["colors"])
