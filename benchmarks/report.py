"""Regenerate BENCHMARKS.md from measurements: nothing in it is typed by hand.

    .venv/bin/python benchmarks/report.py [--quick] [--out BENCHMARKS.md]

Runs, each in its own processes: `mls-mpm bench gradient` (speed and memory of forward, manual backward and
ti.ad.Tape), `mls-mpm bench scaling` (the same against particles, steps and grid), `mls-mpm bench tradeoff`
on the torus scene (accuracy against time; the guide below is computed from it), benchmarks/render_speed.py
(frame rendering vs simulation), and the start-up time of `mls-mpm run` cold (empty Taichi offline cache) and
warm. Plots go to benchmarks/figures/. GPU figures come from benchmarks/gpu_gradient.md, written from what `bash
benchmarks/gpu.sh` measured on a machine with a GPU (where present).
The tradeoff sweep resumes from renders/tradeoff_report/tradeoff.csv: delete that folder after changing the code.
"""
import csv
import argparse
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MLS_MPM = [sys.executable, "-m", "mls_mpm.cli"]
ROW_BUDGET = 400  # seconds: a tradeoff row still running then is stopped and reported as slower than this
GPU_TABLE = ROOT / "benchmarks" / "gpu_gradient.md"  # `mls-mpm bench gradient --arch gpu --out` on a GPU machine
QUALITY_TABLES = {q: ROOT / "benchmarks" / f"quality_{q}.md" for q in ("default", "fast")}  # bench quality's tables


def run(cmd, env=None):
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env={**os.environ, **(env or {})})
    if res.returncode:
        raise SystemExit(f"failed: {' '.join(map(str, cmd))}\n{res.stderr[-3000:]}")
    return "\n".join(ln for ln in res.stdout.splitlines() if not ln.startswith("[Taichi]"))


def startup(cache_dir):
    """Seconds of `mls-mpm run` on a 1-step, 0-iteration copy of the torus scene (start-up + one step)."""
    out = Path(tempfile.mkdtemp())
    cmd = MLS_MPM + ["run", "scenes/circle_to_torus.toml", "--out", str(out), "--no-render", "--quiet",
                     "--set", "sim.steps=1", "--set", "control.stride=1", "--set", "optimize.iterations=0"]
    t0 = time.perf_counter()
    run(cmd, env={"TI_OFFLINE_CACHE_FILE_PATH": str(cache_dir)})
    shutil.rmtree(out, ignore_errors=True)
    return time.perf_counter() - t0


def guide(table):
    """'To go faster, change X; it costs Y': every tradeoff row against the scene's own settings."""
    with open(table, newline="") as fh:
        every = list(csv.DictReader(fh))
    rows = [r for r in every if r["status"] == "ok"]
    over = [r for r in every if r["status"] != "ok"]
    base = next(r for r in rows if r["row"] == "base")
    t0, q0, i0 = float(base["wall_seconds"]), float(base["loss_ratio"]), float(base["iou"] or "nan")
    lines = ["| change | time vs scene settings | loss_final / loss_initial | iou | verdict |", "|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: float(r["wall_seconds"])):
        t, q, i = float(r["wall_seconds"]), float(r["loss_ratio"]), float(r["iou"] or "nan")  # "": none (target_iou)
        if r["row"] == "base":
            verdict = "reference"
        else:  # loss ratios span decades: compare them as a factor
            better = "better" if q < q0 else "worse"
            verdict = (f"{'faster' if t < t0 else 'slower'}; {'also ' if t < t0 and q < q0 else ''}"
                       f"{better}: {q / q0:.3g}x the loss ratio")
        lines.append(f"| {r['row']} (`{r['overrides'] or '-'}`) | {t / t0:.2f}x ({t:.0f} s) | {q:.3g} | {i:.3f} "
                     f"(base {i0:.3f}) | {verdict} |")
    for r in over:
        lines.append(f"| {r['row']} (`{r['overrides']}`) | > {float(r['wall_seconds']) / t0:.0f}x (> "
                     f"{float(r['wall_seconds']):.0f} s) | - | - | {r['status']} |")
    return "\n".join(lines)


def gpu_section():
    """The GPU table measured on a GPU machine (benchmarks/gpu_gradient.md), or why there is none."""
    if GPU_TABLE.is_file():
        return GPU_TABLE.read_text().strip()
    return ("No GPU figures: no session so far has had a GPU machine. The GPU code path itself is tested on every "
            "CI run on Mesa's lavapipe (a Vulkan driver on the CPU, tests/test_gpu.py), where timings mean nothing.")


def quality_section():
    """The morph quality tables (`mls-mpm bench quality`, about 30 minutes at --quality default, run apart from this
    report and copied from DIR/quality.md into benchmarks/quality_<quality>.md), or where they would come from."""
    parts = []
    for q, path in QUALITY_TABLES.items():
        if path.is_file():
            parts.append(f"### `--quality {q}`\n\n" + path.read_text().strip())
        else:
            parts.append(f"### `--quality {q}`\n\nNot measured yet: run `mls-mpm bench quality --quality {q} --out "
                         f"renders/bench_quality_{q}` on a quiet machine and copy its quality.md to {path.name}.")
    return "\n\n".join(parts)


def machine():
    import taichi

    from mls_mpm.bench.child import cpu_model

    taichi_version = ".".join(map(str, taichi.__version__))
    python = platform.python_version()
    return f"{cpu_model()} x {os.cpu_count()}; Python {python}; Taichi {taichi_version}; {platform.system()}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer steps (a smoke run, not for the record)")
    p.add_argument("--out", default=str(ROOT / "BENCHMARKS.md"))
    args = p.parse_args(argv)
    quick = ["--quick"] if args.quick else []
    figures = ROOT / "benchmarks" / "figures"
    figures.mkdir(exist_ok=True)
    gradient = run(MLS_MPM + ["bench", "gradient"] + quick)
    scaling = run(MLS_MPM + ["bench", "scaling", "--out", str(figures)] + quick)
    sweep = ROOT / "renders" / ("tradeoff_report_quick" if args.quick else "tradeoff_report")
    tradeoff = run(MLS_MPM + ["bench", "tradeoff", "scenes/circle_to_torus.toml", "--out", str(sweep),
                              "--max-seconds", str(ROW_BUDGET)] + quick)
    shutil.copy(sweep / "tradeoff.png", figures / "tradeoff.png")
    render = run([sys.executable, "benchmarks/render_speed.py"] + (["--repeats", "5"] if args.quick else []))
    cache = Path(tempfile.mkdtemp())
    cold = startup(cache)
    warm = startup(cache)
    shutil.rmtree(cache, ignore_errors=True)
    text = f"""# Benchmarks

Generated by `.venv/bin/python benchmarks/report.py{' --quick' if args.quick else ''}` on {time.strftime('%Y-%m-%d')}.
Machine: {machine()}.

## Gradient: forward, hand-written backward, ti.ad.Tape (`mls-mpm bench gradient`)

Targets: manual backward <= 1.5x forward; manual forward+backward >= 1.5x faster than Tape; manual
memory <= 0.55x Tape's; forward >= 10M particle-steps/s on 2 CPU threads (f32, 64^2, ~8k particles);
f64 at 32^2 with 1,245 particles: forward <= 0.25 ms/step, backward <= 0.3 ms/step (the thesis's C++ program:
about 1.0 and 1.2 ms/step, single thread).

{gradient}

### On a GPU (`mls-mpm bench gradient --arch gpu --out benchmarks/gpu_gradient.md`)

{gpu_section()}

## Scaling (`mls-mpm bench scaling`)

One quantity varied at a time from the f32, 64^2, 8k-particle case. ![scaling](benchmarks/figures/scaling.png)

{scaling}

## Speed against accuracy (`mls-mpm bench tradeoff scenes/circle_to_torus.toml{' --quick' if args.quick else ''} --max-seconds {ROW_BUDGET}`)

Each row changes one setting of the torus scene{' (2 temporal iterations / optimizer steps, as in `--quick`)' if args.quick else ''}
and is one `mls-mpm run` process, its wall time including start-up and kernel compilation; a row still running
after {ROW_BUDGET} s is stopped. Loss ratios of rows that change the loss itself (loss grids, penalty) are not
comparable to the others; compare their iou. ![tradeoff](benchmarks/figures/tradeoff.png)

```
{tradeoff}
```

To go faster, change X; it costs Y (computed from the sweep above):

{guide(sweep / "tradeoff.csv")}

## Morph quality (`mls-mpm bench quality`)

Targets (issue 11): at `--quality default` every pair iou >= 0.90 and mass_error <= 0.15 in <= 120 s wall (compile
included), median iou >= 0.95; at `--quality fast` iou >= 0.8 in <= 30 s. iou compares the nodes of the finest loss
grid holding more than 10% of the rest node mass (problem.occupied); mass_error is 1/2 sum |m_i - m_iu| / sum m_iu
there.

{quality_section()}

## Rendering (`python benchmarks/render_speed.py`)

```
{render}
```

## Start-up: `mls-mpm run` to the first simulated step

`mls-mpm run scenes/circle_to_torus.toml --set sim.steps=1 --set control.stride=1 --set optimize.iterations=0
--no-render` (import, scene, sampling, kernel compilation, one forward step and the loss), with an empty Taichi
offline cache (cold) and again with the cache it filled (warm). Goal: <= 10 s cold, <= 2 s warm.

| cold | warm |
|---|---|
| {cold:.1f} s | {warm:.1f} s |
"""
    Path(args.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
