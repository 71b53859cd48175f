"""`mls-mpm bench tradeoff SCENE`: what each setting that trades time for accuracy buys, measured.

Every row is one `mls-mpm run` of the scene with a few `--set` overrides, in its own process and folder; it
records wall time and the accuracy reached (loss_final / loss_initial, iou, mass_outside_target). Rows vary
one setting at a time from the scene's own settings. Rows already in tradeoff.csv are skipped, so an
interrupted sweep resumes. The Pareto front (no other row both faster and more accurate in loss) is marked in
tradeoff.png and printed. A row stopped at its time budget (--max-seconds) is measured again by a sweep
with a larger budget.
"""
import csv
import json
import math
import re
import subprocess
import sys
import time
from pathlib import Path

from PIL import Image, ImageDraw

from .. import plot
from ..checkpoint import atomic_write
from .output import writable_folder

FIELDS = ["row", "group", "overrides", "wall_seconds", "loss_ratio", "iou", "mass_outside_target", "iterations",
          "converged", "status"]


def rows_for(scene, quick):
    """(row name, group, overrides) one setting at a time from the scene's settings."""
    sim, opt = scene.sim, scene.optimize
    base = [] if not quick else [f"optimize.iterations={min(opt.iterations, 2)}"]
    rows = [("base", "base", [])]

    def grid(n):  # keep dt under the CFL limit and the simulated time fixed
        k = n / sim.n_grid
        steps = max(1, round(sim.steps * k))
        return [f"sim.n_grid={n}", f"sim.dt={sim.dt / k!r}", f"sim.steps={steps}",
                f"control.stride={max(1, min(steps, round(sim.stride * k)))}",
                f"loss.grids={[max(4, round(g * k)) for g in scene.loss.grids]}"]

    grids = (32, 64) if quick else (32, 64, 128)
    rows += [(f"n_grid={n}", "grid", grid(n)) for n in grids if n != sim.n_grid]
    rows += [(f"ppc={p}", "particles per cell", [f"sim.particles_per_cell={p}"])
             for p in ((1, 4) if quick else (1, 4, 9)) if p != sim.particles_per_cell]
    rows += [(f"stride={s}", "control stride", [f"control.stride={s}"])
             for s in ((5, 25) if quick else (1, 5, 10, 25)) if s != sim.stride and s <= sim.steps]
    if not quick:
        rows += [(f"iterations={i}", "iterations", [f"optimize.iterations={i}"]) for i in (1, 2, 4, 8)
                 if i != opt.iterations]
        rows.append(("converged", "iterations", ["optimize.iterations=200", "optimize.tol=1e-4"]))
    methods = [("adam", ["optimize.lr=0.02"]), ("lbfgs", [])] + ([] if opt.method == "gd" else [("gd", [])])
    rows += [(f"method={m}", "optimizer", [f"optimize.method={m}"] + extra) for m, extra in methods
             if m != opt.method]
    if scene.loss.kind in ("mass", "log_mass"):
        finest = max(scene.loss.grids)
        multi = [max(4, finest // 2), finest] if len(scene.loss.grids) == 1 else [finest]
        rows.append((f"grids={multi}", "loss grids", [f"loss.grids={multi}", f"loss.weights={[1.0] * len(multi)}"]))
        rows.append(("penalty=off" if scene.loss.penalty else "penalty=10", "penalty",
                     ["loss.penalty=0" if scene.loss.penalty else "loss.penalty=10"]))
    rows.append(("f32" if sim.dtype == "f64" else "f64", "dtype", [f"sim.dtype={'f32' if sim.dtype == 'f64' else 'f64'}"]))
    return [(name, group, base + ov) for name, group, ov in rows]


def measure(scene_path, name, overrides, out_dir, max_seconds=None):
    """Run one row in its own process; (wall seconds, summary dict or None, status).

    A row still running after max_seconds is stopped and recorded as over the budget (no accuracy figures).
    """
    cmd = [sys.executable, "-m", "mls_mpm.cli", "run", str(scene_path), "--out", str(out_dir), "--no-render",
           "--quiet"]
    for ov in overrides:
        cmd += ["--set", ov]
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=max_seconds)
    except subprocess.TimeoutExpired:
        return time.perf_counter() - t0, None, f"stopped: over the {max_seconds:g} s budget of a row"
    wall = time.perf_counter() - t0
    summary_path = Path(out_dir) / "summary.json"
    if res.returncode or not summary_path.is_file():
        err = (res.stderr.strip().splitlines() or ["failed"])[-1]
        return wall, None, err[:200]
    return wall, json.loads(summary_path.read_text()), "ok"


def pareto(rows):
    """Rows not dominated in (wall_seconds, loss_ratio), both lower is better."""
    ok = [r for r in rows if r["status"] == "ok"]
    front = []
    for r in ok:
        t, q = float(r["wall_seconds"]), float(r["loss_ratio"])
        if not any(float(o["wall_seconds"]) <= t and float(o["loss_ratio"]) <= q and
                   (float(o["wall_seconds"]) < t or float(o["loss_ratio"]) < q) for o in ok):
            front.append(r)
    return sorted(front, key=lambda r: float(r["wall_seconds"]))


def bench_tradeoff(scene_path, out=None, quick=False, emit=print, max_seconds=None):
    """The sweep of `rows_for`, resumable; max_seconds: the wall-time budget of one row (None: no limit)."""
    from ..scene import load_scene

    scene = load_scene(scene_path)
    out = writable_folder(out or Path("renders") / f"tradeoff_{scene.name}{'_quick' if quick else ''}")
    table = out / "tradeoff.csv"
    done = {}
    if table.is_file():
        with open(table, newline="") as fh:
            done = {r["row"]: r for r in csv.DictReader(fh)}
    plan = rows_for(scene, quick)
    measured = sum(not _retry(r, max_seconds) for r in done.values())
    emit(f"tradeoff sweep of {scene.name}: {len(plan)} rows ({measured} already measured) -> {out}")
    for i, (name, group, overrides) in enumerate(plan, 1):
        earlier = name in done and not _retry(done[name], max_seconds)
        if not earlier:
            wall, summary, status = measure(scene.path, name, overrides, out / "runs" / _slug(name), max_seconds)
            row = {"row": name, "group": group, "overrides": " ".join(overrides), "wall_seconds": f"{wall:.2f}",
                   "status": status}
            if summary:
                row.update(loss_ratio=f"{summary['loss_final'] / summary['loss_initial']:.6g}",
                           iou="" if summary["iou"] is None else f"{summary['iou']:.4f}",
                           mass_outside_target=f"{summary['mass_outside_target']:.4f}",
                           iterations=summary["iterations"], converged=summary["converged"])
            done[name] = row
            _write_csv(table, [done[n] for n, _, _ in plan if n in done])
        row = done[name]
        status = row["status"] if row["status"] != "ok" else ""
        emit(f"[{i}/{len(plan)}] {name:<22s} {float(row['wall_seconds']):7.1f} s  loss ratio "
             f"{row.get('loss_ratio') or '-':>10s}  iou {row.get('iou') or '-':>6s}  {status}"
             f"{'  (measured earlier)' if earlier else ''}")
    rows = [done[n] for n, _, _ in plan if n in done]
    front = pareto(rows)
    scatter(rows, front, out / "tradeoff.png", f"{scene.name}: accuracy against time")
    emit("Pareto-optimal settings (faster and more accurate than no other row):")
    for r in front:
        emit(f"  {r['row']:<22s} {float(r['wall_seconds']):7.1f} s  loss ratio {float(r['loss_ratio']):.3g}  "
             f"iou {r['iou']}  ({r['overrides'] or 'scene settings'})")
    return rows, front


def _retry(row, max_seconds):
    """Whether a row already in the table is measured again: one stopped at a smaller budget than this one."""
    budget = re.fullmatch(r"stopped: over the (\S+) s budget of a row", row["status"])
    return bool(budget) and (max_seconds is None or max_seconds > float(budget.group(1)))


def _slug(name):
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def _write_csv(path, rows):
    def write(fh):
        import io

        text = io.StringIO()
        w = csv.DictWriter(text, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
        fh.write(text.getvalue().encode())

    atomic_write(path, write)


def scatter(rows, front, path, title, size=(720, 480)):
    """Loss ratio (log) against wall time (log), every row a labelled dot, the Pareto front joined in red."""
    ok = [r for r in rows if r["status"] == "ok" and float(r["loss_ratio"]) > 0]
    W, H = size
    left, right, top, bottom = 70, 20, 30, 46
    pw, ph = W - left - right, H - top - bottom
    img = Image.new("RGB", size, "white")
    d = ImageDraw.Draw(img)
    font = plot.font()
    plot.text(d, (left + pw / 2, 8), title, font, anchor="mt")
    plot.text(d, (left + pw / 2, H - 8), "wall time (s, log)", font, anchor="mb")
    plot.text(d, (6, top - 14), "loss_final / loss_initial (log)", font)
    if not ok:
        d.rectangle([left, top, left + pw, top + ph], outline="black")
    else:
        xs = [math.log10(float(r["wall_seconds"])) for r in ok]
        ys = [math.log10(float(r["loss_ratio"])) for r in ok]
        x0, x1 = math.floor(min(xs) * 4) / 4, math.ceil(max(xs) * 4) / 4 + 0.25
        y0, y1 = math.floor(min(ys)), math.ceil(max(ys)) + (1 if math.ceil(max(ys)) == math.floor(min(ys)) else 0)
        axes = plot.Axes(left, top, pw, ph, (x0, x1), (y0, y1))
        for v, label in plot.decade_ticks(y0, y1):
            axes.y_tick(d, v, label, font, tick=0, gap=6, grid=(230, 230, 230))
        for v, label in plot.log_125_ticks(x0, x1):
            axes.x_tick(d, v, label, font, tick=4, gap=2)
        axes.frame(d)
        fr = [axes.pt(math.log10(float(r["wall_seconds"])), math.log10(float(r["loss_ratio"]))) for r in front]
        if len(fr) > 1:
            d.line(fr, fill=(200, 30, 30), width=2)
        names = {r["row"] for r in front}
        for r, x, y in zip(ok, xs, ys):
            px, py = axes.pt(x, y)
            color = (200, 30, 30) if r["row"] in names else (40, 40, 160)
            d.ellipse([px - 3, py - 3, px + 3, py + 3], fill=color)
            plot.text(d, (px + 5, py), r["row"], font, anchor="lm", fill=color)
    atomic_write(path, lambda fh: img.save(fh, format="PNG"))
