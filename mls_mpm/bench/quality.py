"""`mls-mpm bench quality`: how close `mls-mpm morph` gets, and how fast, on a suite of shape pairs.

The 2D pairs are drawn by scenes/make_images.py into scenes/images/pairs/ (<name>_initial.png, <name>_target.png);
PAIRS lists them with the category each covers and what it tests. The 3D suite (dim=3, `--dim 3`) is pairs3d.PAIRS:
built-in solids, meshes that trimesh writes into <out>/meshes/ first, an extruded colour pair. Every pair runs
through `mls-mpm morph` in a process of its own, `workers` at a time, each with cores // workers Taichi threads
(`--set sim.threads=T`), into <out>/<name>/, and the figures are read back from its summary.json: iou, mass_error
(total-variation distance of the node masses on the finest loss grid), mass_outside_target, color_error for a colour
pair, and the wall time of the whole process (start-up and compilation included), which is what the targets bound.
Each pair compiles in an empty Taichi offline cache of its own (removed afterwards), as a first run on a machine
does (and a new 2D shape, or a 3D one in a capacity not compiled before: mls_mpm/sizes.py); warm_cache=True
(--warm-cache) uses the user's cache instead, where an earlier run of the same pair leaves every kernel compiled. A
pair whose process fails gets a row with its last stderr line and the suite goes on. The table (quality.md, ready
for BENCHMARKS.md) and quality.csv are written atomically once every pair has finished.
"""
import contextlib
import csv
import io
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

from ..checkpoint import atomic_write
from . import pairs3d
from .child import cpu_model
from .output import BenchError, writable_folder
from .pairs3d import PAIRS_DIR
DEFAULT_OUT = Path("renders") / "bench_quality"
DEFAULT_OUT_3D = Path("renders") / "bench_quality_3d"
QUALITIES = ("fast", "default", "best")

# What the suite has to cover; every pair names the one it stands for.
CATEGORIES = ("area 1/3", "area 3", "off-centre", "thin", "hole opens", "hole closes", "split", "merge", "letter",
              "colour")


@dataclass(frozen=True)
class Pair:
    name: str
    category: str  # one of CATEGORIES
    tests: str  # what the pair tests, one phrase

    @property
    def initial(self) -> Path:
        return PAIRS_DIR / f"{self.name}_initial.png"

    @property
    def target(self) -> Path:
        return PAIRS_DIR / f"{self.name}_target.png"

    def inputs(self, meshes=None) -> tuple[str, str]:
        """INITIAL and TARGET for `mls-mpm morph` (as pairs3d.Pair3D.inputs; a 2D pair has no meshes)."""
        return str(self.initial), str(self.target)

    def images(self) -> list[Path]:
        """The shipped images the pair morphs."""
        return [self.initial, self.target]


PAIRS = (
    Pair("shrink_disk", "area 1/3", "disk to a disk of 1/3 the area"),
    Pair("grow_square", "area 3", "square to a square of 3x the area"),
    Pair("corner_disk", "off-centre", "disk to the same disk in the top-right corner"),
    Pair("side_crescent", "off-centre", "disk to a crescent on the left, thin tips"),
    Pair("thin_ring", "thin", "disk to a 6 px ring around it"),
    Pair("letter_L_thin", "thin", "square to an L of 6 px strokes"),
    Pair("hole_opens", "hole opens", "disk to an annulus"),
    Pair("hole_closes", "hole closes", "annulus to a disk"),
    Pair("split_two", "split", "disk to two disks"),
    Pair("split_three", "split", "disk to three disks"),
    Pair("merge_two", "merge", "two disks grow into one ellipse"),
    Pair("letter_T", "letter", "square to a T"),
    Pair("letter_C", "letter", "disk to a C (round strokes)"),
    Pair("letter_S", "letter", "square to an S (round strokes)"),
    Pair("letter_A", "letter", "disk to an A with its hole"),
    Pair("color_bar_to_disk", "colour", "red-blue bar to a blue-red disk: colours trade sides"),
)
QUICK = ("corner_disk", "split_two", "letter_T")  # --quick: one move, one split, one glyph, at --quality fast


@dataclass(frozen=True)
class Target:
    """A pair passes with iou >= iou, mass_error <= mass_error and wall time <= wall_seconds (None: no bound)."""
    iou: float
    mass_error: float = None
    wall_seconds: float = None

    def describe(self):
        parts = [f"iou >= {self.iou:.2f}"]
        if self.mass_error is not None:
            parts.append(f"mass_error <= {self.mass_error:.2f}")
        if self.wall_seconds is not None:
            parts.append(f"wall <= {self.wall_seconds:g} s")
        return ", ".join(parts)


# The targets of the quality levels; `best` has no time bound of its own and keeps the default's accuracy bounds.
TARGETS = {"fast": Target(0.80, None, 30.0), "default": Target(0.90, 0.15, 120.0), "best": Target(0.90, 0.15)}
# 3D: the same accuracy; the wall bounds are the presets' budgets (morph.QUALITIES_3D: 120 s at fast and default)
# plus a minute for start-up and the 3D kernels' compilation in an empty cache
TARGETS_3D = {"fast": Target(0.80, None, 60.0), "default": Target(0.90, 0.15, 180.0), "best": Target(0.90, 0.15)}
SUITES = {2: (PAIRS, QUICK, TARGETS), 3: (pairs3d.PAIRS, pairs3d.QUICK, TARGETS_3D)}

FIELDS = ["pair", "category", "tests", "iou", "mass_error", "mass_outside_target", "color_error", "wall_seconds",
          "run_seconds", "stop_reason", "result"]


def select(names=None, quick=False, dim=2):
    """The pairs of the dim's suite named (a list, in suite order), its quick subset, or all; BenchError for an
    unknown name (naming the --dim that has it, if the other suite does)."""
    pairs, quick_names, _ = SUITES[dim]
    by_name = {p.name: p for p in pairs}
    if names is None:
        names = quick_names if quick else [p.name for p in pairs]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        other = 5 - dim
        elsewhere = [n for n in unknown if n in {p.name for p in SUITES[other][0]}]
        hint = f" ({elsewhere[0]} is a pair of --dim {other})" if elsewhere else ""
        raise BenchError(f"bench quality: --pairs {','.join(unknown)}: no such pair{hint}; expected names from "
                         f"{', '.join(by_name)}")
    wanted = set(names)
    return [p for p in pairs if p.name in wanted]


def threads_per_worker(workers):
    """cores // workers, at least 1, cores being those this process may run on."""
    return max(1, len(os.sched_getaffinity(0)) // workers)


def morph_command(pair, out_dir, quality, threads, overrides=(), meshes=None):
    """The `mls-mpm morph` command line of one pair, in this interpreter; user overrides come last and win.
    meshes: the folder of a 3D pair's meshes (pairs3d.write_meshes)."""
    cmd = [sys.executable, "-m", "mls_mpm.cli", "morph", *pair.inputs(meshes), "--out", str(out_dir),
           "--quality", quality, "--no-render", "--quiet", "--set", f"sim.threads={threads}"]
    for ov in overrides:
        cmd += ["--set", ov]
    return cmd


CACHE_VARIABLE = "TI_OFFLINE_CACHE_FILE_PATH"  # where Taichi keeps the kernels it compiled


def run_pair(pair, out_dir, quality, threads, overrides=(), warm_cache=False, meshes=None):
    """Morph one pair in its own process; its row (figures as numbers, "result" judged later by `judge`).
    warm_cache=False: in an empty Taichi cache of its own (module docstring); meshes: as morph_command."""
    env = {**os.environ, "TI_LOG_LEVEL": "error"}
    t0 = time.perf_counter()
    with (contextlib.nullcontext() if warm_cache else
          tempfile.TemporaryDirectory(prefix="mls_mpm_quality_cache_", ignore_cleanup_errors=True)) as cache:
        if cache is not None:
            env[CACHE_VARIABLE] = cache
        res = subprocess.run(morph_command(pair, out_dir, quality, threads, overrides, meshes), capture_output=True,
                             text=True, env=env)
    row = {"pair": pair.name, "category": pair.category, "tests": pair.tests,
           "wall_seconds": time.perf_counter() - t0}
    summary_path = Path(out_dir) / "summary.json"
    if res.returncode:
        last = (res.stderr.strip().splitlines() or [f"exit {res.returncode}"])[-1]
        return dict(row, error=f"exit {res.returncode}: {last[:200]}")
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, ValueError) as e:
        return dict(row, error=f"{summary_path}: unreadable ({getattr(e, 'strerror', None) or e})")
    for key in ("iou", "mass_error", "mass_outside_target", "color_error"):
        if isinstance(summary.get(key), (int, float)):
            row[key] = float(summary[key])
    if isinstance(summary.get("wall_seconds"), (int, float)):
        row["run_seconds"] = float(summary["wall_seconds"])
    reasons = summary.get("stop_reason")
    row["stop_reason"] = "; ".join(map(str, reasons)) if isinstance(reasons, list) else str(reasons or "")
    return row


def judge(row, target):
    """"pass", "fail: <what missed>" or "error: <why the process failed>"."""
    if "error" in row:
        return f"error: {row['error']}"
    missed = []
    if row.get("iou") is None or row["iou"] < target.iou:
        missed.append(f"iou {_num(row.get('iou'))} < {target.iou:.2f}")
    if target.mass_error is not None and (row.get("mass_error") is None or row["mass_error"] > target.mass_error):
        missed.append(f"mass_error {_num(row.get('mass_error'))} > {target.mass_error:.2f}")
    if target.wall_seconds is not None and row["wall_seconds"] > target.wall_seconds:
        missed.append(f"wall {row['wall_seconds']:.0f} s > {target.wall_seconds:g} s")
    return "fail: " + ", ".join(missed) if missed else "pass"


def suite_figures(rows):
    """Worst and median iou and mass_error over the pairs that reported them: {"iou": (worst, median, worst pair),
    "mass_error": (...)}; a figure no pair reported is absent."""
    out = {}
    for key, worst in (("iou", min), ("mass_error", max)):
        have = [r for r in rows if r.get(key) is not None]
        if have:
            w = worst(have, key=lambda r: r[key])
            out[key] = (w[key], statistics.median(r[key] for r in have), w["pair"])
    return out


def command_line(quality, quick, workers, out, names, overrides, warm_cache=False, dim=2):
    """The `mls-mpm bench quality` command that repeats this run."""
    argv = ["mls-mpm", "bench", "quality"] + (["--dim", "3"] if dim == 3 else []) + (["--quick"] if quick else [])
    argv += ["--quality", quality, "--workers", str(workers), "--out", str(out)]
    if warm_cache:
        argv.append("--warm-cache")
    if names is not None:
        argv += ["--pairs", ",".join(names)]
    for ov in overrides:
        argv += ["--set", ov]
    return shlex.join(argv)


def _num(v, fmt=".3f"):
    return "-" if v is None else format(v, fmt)


def _count(n, noun):
    return f"{n} {noun}{'' if n == 1 else 's'}"


def _cell(text):
    return str(text).replace("|", "\\|")


def table(rows, quality, workers, threads, command, warm_cache=False, dim=2):
    """quality.md: the settings line, one row per pair, the suite's worst and median, the CPU and the command."""
    target = SUITES[dim][2][quality]
    where = ("scenes/images/pairs/" if dim == 2 else
             "3D: built-in solids, trimesh meshes, extruded images; mls_mpm/bench/pairs3d.py")
    n_pass = sum(r["result"] == "pass" for r in rows)
    cache = ("Taichi's cache as it was (kernels an earlier run compiled are not compiled again)" if warm_cache else
             "each in an empty Taichi cache (every kernel compiles, as for a shape of your own)")
    lines = [f"`mls-mpm morph --quality {quality}` on {_count(len(rows), 'shape pair')} ({where}), "
             f"{workers} at a time, {_count(threads, 'Taichi thread')} each, {cache}. Target per pair: "
             f"{target.describe()} (wall: the whole process, start-up and compilation included).", "",
             "| pair | tests | iou | mass_error | mass outside | colour error | wall s | result |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['pair']} | {_cell(r['tests'])} | {_num(r.get('iou'))} | {_num(r.get('mass_error'))} | "
                     f"{_num(r.get('mass_outside_target'))} | {_num(r.get('color_error'))} | "
                     f"{r['wall_seconds']:.1f} | {_cell(r['result'])} |")
    lines.append("")
    figures = suite_figures(rows)
    for key in ("iou", "mass_error"):
        if key in figures:
            worst, median, where = figures[key]
            lines.append(f"- {key}: worst {worst:.3f} ({where}), median {median:.3f}")
        else:
            lines.append(f"- {key}: no pair reported it")
    failed = sum(r["result"].startswith("error") for r in rows)
    lines.append(f"- {n_pass} of {len(rows)} pairs meet the target" +
                 (f"; {failed} did not finish (their error is in the table)" if failed else ""))
    lines.append(f"- CPU: {cpu_model()}, {_count(len(os.sched_getaffinity(0)), 'core')} available")
    lines.append(f"- command: `{command}`")
    return "\n".join(lines) + "\n"


def _csv_text(rows):
    text = io.StringIO()
    w = csv.DictWriter(text, fieldnames=FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({**r, **{k: ("" if r.get(k) is None else f"{r[k]:.6g}") for k in
                            ("iou", "mass_error", "mass_outside_target", "color_error")},
                    "wall_seconds": f"{r['wall_seconds']:.2f}",
                    "run_seconds": "" if r.get("run_seconds") is None else f"{r['run_seconds']:.2f}"})
    return text.getvalue()


def bench_quality(quality=None, quick=False, workers=1, out=None, names=None, overrides=(), emit=print,
                  warm_cache=False, dim=2):
    """Run the dim's suite (or the pairs named, or the quick subset at fast quality); write quality.md and
    quality.csv in out (default renders/bench_quality/, 3D: renders/bench_quality_3d/); returns the rows in suite
    order. warm_cache: see run_pair."""
    if quick and names is not None:
        raise BenchError("bench quality: --quick and --pairs: --quick picks its own pairs; give one of them")
    if workers < 1:
        raise BenchError(f"bench quality: --workers {workers}: expected an integer >= 1")
    quality = quality or ("fast" if quick else "default")
    if quality not in QUALITIES:
        raise BenchError(f"bench quality: --quality {quality}: expected one of {', '.join(QUALITIES)}")
    pairs = select(names, quick, dim)
    missing = [str(p) for pair in pairs for p in pair.images() if not p.is_file()]
    if missing:
        raise BenchError(f"bench quality: {missing[0]}: no such image ({len(missing)} missing); draw them with "
                         "python scenes/make_images.py")
    out = writable_folder(out or (DEFAULT_OUT if dim == 2 else DEFAULT_OUT_3D))
    threads = threads_per_worker(workers)
    command = command_line(quality, quick, workers, out, names, overrides, warm_cache, dim)
    meshes = None
    if dim == 3:
        wanted = sorted({t for p in pairs for t in (p.initial_text, p.target_text) if t in pairs3d.MESHES})
        meshes = pairs3d.write_meshes(out / "meshes", wanted) if wanted else None
    emit(f"quality benchmark: {_count(len(pairs), f'{dim}D pair')} at --quality {quality}, {workers} at a time with "
         f"{_count(threads, 'thread')} each, {'a warm' if warm_cache else 'each in an empty'} Taichi cache -> {out}")
    rows = {}
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        running = [pool.submit(run_pair, p, out / p.name, quality, threads, overrides, warm_cache, meshes)
                   for p in pairs]
        for done, future in enumerate(as_completed(running), 1):
            row = future.result()
            row["result"] = judge(row, SUITES[dim][2][quality])
            rows[row["pair"]] = row
            emit(f"[{done}/{len(pairs)}] {row['pair']:<18s} iou {_num(row.get('iou')):>5s}  mass_error "
                 f"{_num(row.get('mass_error')):>5s}  outside {_num(row.get('mass_outside_target')):>5s}  "
                 f"{row['wall_seconds']:6.1f} s  {row['result']}")
    finally:  # Ctrl-C: pairs not yet started are dropped; running ones got the signal too (same process group)
        pool.shutdown(wait=True, cancel_futures=True)
    rows = [rows[p.name] for p in pairs]
    md = table(rows, quality, workers, threads, command, warm_cache, dim)
    atomic_write(out / "quality.md", lambda fh: fh.write(md.encode()))
    atomic_write(out / "quality.csv", lambda fh: fh.write(_csv_text(rows).encode()))
    emit("")
    emit(md.rstrip("\n"))
    emit(f"written: {out / 'quality.md'}, {out / 'quality.csv'}")
    return rows
