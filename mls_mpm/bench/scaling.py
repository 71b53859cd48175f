"""`mls-mpm bench scaling`: forward, manual backward and Tape ms/step and peak memory against particles, steps
and grid, one quantity varied at a time from the large case; the table, and scaling.png (log-log panels)."""
import math
from pathlib import Path

from PIL import Image, ImageDraw

from .. import plot
from ..checkpoint import atomic_write
from .child import CASES, run_child
from .output import writable_folder

SWEEPS = {
    "particles": [1024, 4096, 16384, 65536],
    "steps": [50, 200, 800],
    "n_grid": [32, 64, 128, 256],
}


def bench_scaling(quick=False, emit=print, plot_path="scaling.png"):
    """Print the scaling table, write plot_path (its folder is created and proved writable first)."""
    from ..config import SimConfig
    from ..memory import estimate_bytes

    writable_folder(Path(plot_path).parent)
    base = dict(CASES["large"], steps=100 if quick else 200)
    results = {}
    emit("| varied | value | fwd ms/step | manual bwd ms/step | Tape fwd+bwd ms/step | manual peak MiB | "
         "Tape peak MiB | field estimate MiB |")
    emit("|---|---|---|---|---|---|---|---|")
    for key, values in SWEEPS.items():
        for v in values[:3] if quick else values:
            case = dict(base, **{key: v})
            steps = case["steps"]
            man = run_child(case, "manual", steps)
            tape = run_child(case, "tape", steps)
            cfg = SimConfig(n_grid=case["n_grid"], steps=steps, stride=10, dtype=case["dtype"])
            est = estimate_bytes(cfg, case["particles"]) / 2 ** 20
            results.setdefault(key, []).append((v, man["forward_ms"], man["backward_ms"], tape["tape_ms"]))
            emit(f"| {key} | {v} | {man['forward_ms']:.3f} | {man['backward_ms']:.3f} | {tape['tape_ms']:.3f} | "
                 f"{man['peak_mib']:.0f} | {tape['peak_mib']:.0f} | {est:.0f} |")
    per = 12 * 4  # x, v, C, F: 12 f32 words per particle-step (memory.estimate_bytes)
    node = 3 * 4  # m, p: 3 f32 words per grid node and stored step (memory.parts; v has one slot)
    emit(f"\nField memory grows linearly in particles x steps: {per} bytes per particle-step in f32 (twice that in "
         f"f64), plus {node} bytes per grid node per step (64^2: {node * 64 * 64 // 1024} KiB per step). 24 GiB "
         f"holds about "
         f"{24 * 2 ** 30 / per / 1e6:.0f} million particle-steps in f32, e.g. 64k particles x "
         f"{24 * 2 ** 30 / per / 65536:.0f} steps; Simulator refuses larger scenes up front (sim.max_memory_gb).")
    plot_scaling(results, plot_path)
    return results


def plot_scaling(results, path):
    """Three log-log panels: ms/step of forward, manual backward and Tape against each varied quantity.

    results: {varied quantity: [(value, forward ms, manual backward ms, Tape ms), ...]}."""
    W, H, pad = 300, 260, 46
    img = Image.new("RGB", (W * len(results), H), "white")
    d = ImageDraw.Draw(img)
    font = plot.font()
    colors = [(30, 30, 180), (200, 30, 30), (30, 140, 30)]
    for k, (key, pts) in enumerate(results.items()):
        ox = k * W
        xs = [math.log10(p[0]) for p in pts]
        ys = [math.log10(y) for p in pts for y in p[1:]]
        y0, y1 = math.floor(min(ys)), math.ceil(max(ys))
        y1 += y1 == y0
        axes = plot.Axes(ox + pad, 20, W - pad - 10, H - pad - 20, (min(xs) - 0.1, max(xs) + 0.1), (y0, y1))
        axes.frame(d)
        plot.text(d, (ox + W / 2, H - 14), f"{key} (log)", font, anchor="mm")
        for v, label in plot.decade_ticks(y0, y1):
            axes.y_tick(d, v, label, font, tick=3, gap=2)
        for p in pts:
            axes.x_tick(d, math.log10(p[0]), str(p[0]), font, tick=3, gap=2)
        for c, label in enumerate(("forward", "manual backward", "Tape fwd+bwd")):
            d.line([axes.pt(math.log10(p[0]), math.log10(p[1 + c])) for p in pts], fill=colors[c], width=2)
            if k == 0:
                plot.text(d, (ox + pad + 6, 24 + 12 * c), label, font, fill=colors[c])
        plot.text(d, (ox + pad, 6), "ms per step", font)
    atomic_write(path, lambda fh: img.save(fh, format="PNG"))
