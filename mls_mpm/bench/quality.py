"""`mls-mpm bench quality`: how close `mls-mpm morph` gets, and how fast, on a suite of shape pairs.

The pairs are drawn by scenes/make_images.py into scenes/images/pairs/ (<name>_initial.png, <name>_target.png);
PAIRS lists them with the category each covers and what it tests. Every pair runs through `mls-mpm morph` in a
process of its own, `workers` at a time, each with cores // workers Taichi threads (`--set sim.threads=T`), into
<out>/<name>/, and the figures are read back from its summary.json: iou, mass_error (total-variation distance of
the node masses on the finest loss grid), mass_outside_target, color_error for a colour pair, and the wall time
of the whole process (start-up and compilation included), which is what the targets bound. Each pair compiles in
an empty Taichi offline cache of its own (removed afterwards), as a shape of the user's own does (the particle count
is compiled into the kernels); warm_cache=True (--warm-cache) uses the user's cache instead, where an earlier run
of the same pair leaves every kernel compiled. A pair whose process
fails gets a row with its last stderr line and the suite goes on. The table (quality.md, ready for
BENCHMARKS.md) and quality.csv are written atomically once every pair has finished.
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
from .child import cpu_model
from .output import BenchError, writable_folder

PAIRS_DIR = Path(__file__).resolve().parents[2] / "scenes" / "images" / "pairs"
DEFAULT_OUT = Path("renders") / "bench_quality"
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

FIELDS = ["pair", "category", "tests", "iou", "mass_error", "mass_outside_target", "color_error", "wall_seconds",
          "run_seconds", "stop_reason", "result"]


def select(names=None, quick=False):
    """The pairs named (a list, in suite order), the quick subset, or all; BenchError for an unknown name."""
    by_name = {p.name: p for p in PAIRS}
    if names is None:
        names = QUICK if quick else [p.name for p in PAIRS]
    unknown = [n for n in names if n not in by_name]
    if unknown:
        raise BenchError(f"bench quality: --pairs {','.join(unknown)}: no such pair; expected names from "
                         f"{', '.join(by_name)}")
    wanted = set(names)
    return [p for p in PAIRS if p.name in wanted]


def threads_per_worker(workers):
    """cores // workers, at least 1, cores being those this process may run on."""
    return max(1, len(os.sched_getaffinity(0)) // workers)


def morph_command(pair, out_dir, quality, threads, overrides=()):
    """The `mls-mpm morph` command line of one pair, in this interpreter; user overrides come last and win."""
    cmd = [sys.executable, "-m", "mls_mpm.cli", "morph", str(pair.initial), str(pair.target), "--out", str(out_dir),
           "--quality", quality, "--no-render", "--quiet", "--set", f"sim.threads={threads}"]
    for ov in overrides:
        cmd += ["--set", ov]
    return cmd


CACHE_VARIABLE = "TI_OFFLINE_CACHE_FILE_PATH"  # where Taichi keeps the kernels it compiled


def run_pair(pair, out_dir, quality, threads, overrides=(), warm_cache=False):
    """Morph one pair in its own process; its row (figures as numbers, "result" judged later by `judge`).
    warm_cache=False: in an empty Taichi cache of its own (module docstring)."""
    env = {**os.environ, "TI_LOG_LEVEL": "error"}
    t0 = time.perf_counter()
    with (contextlib.nullcontext() if warm_cache else
          tempfile.TemporaryDirectory(prefix="mls_mpm_quality_cache_", ignore_cleanup_errors=True)) as cache:
        if cache is not None:
            env[CACHE_VARIABLE] = cache
        res = subprocess.run(morph_command(pair, out_dir, quality, threads, overrides), capture_output=True,
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


def command_line(quality, quick, workers, out, names, overrides, warm_cache=False):
    """The `mls-mpm bench quality` command that repeats this run."""
    argv = ["mls-mpm", "bench", "quality"] + (["--quick"] if quick else []) + ["--quality", quality, "--workers",
                                                                                str(workers), "--out", str(out)]
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


def table(rows, quality, workers, threads, command, warm_cache=False):
    """quality.md: the settings line, one row per pair, the suite's worst and median, the CPU and the command."""
    target = TARGETS[quality]
    n_pass = sum(r["result"] == "pass" for r in rows)
    cache = ("Taichi's cache as it was (kernels an earlier run compiled are not compiled again)" if warm_cache else
             "each in an empty Taichi cache (every kernel compiles, as for a shape of your own)")
    lines = [f"`mls-mpm morph --quality {quality}` on {_count(len(rows), 'shape pair')} (scenes/images/pairs/), "
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
                  warm_cache=False):
    """Run the suite (or the pairs named, or the quick subset at fast quality); write quality.md and quality.csv
    in out (default renders/bench_quality/); returns the rows in suite order. warm_cache: see run_pair."""
    if quick and names is not None:
        raise BenchError("bench quality: --quick and --pairs: --quick picks its own pairs; give one of them")
    if workers < 1:
        raise BenchError(f"bench quality: --workers {workers}: expected an integer >= 1")
    quality = quality or ("fast" if quick else "default")
    if quality not in QUALITIES:
        raise BenchError(f"bench quality: --quality {quality}: expected one of {', '.join(QUALITIES)}")
    pairs = select(names, quick)
    missing = [str(p) for pair in pairs for p in (pair.initial, pair.target) if not p.is_file()]
    if missing:
        raise BenchError(f"bench quality: {missing[0]}: no such image ({len(missing)} missing); draw them with "
                         "python scenes/make_images.py")
    out = writable_folder(out or DEFAULT_OUT)
    threads = threads_per_worker(workers)
    command = command_line(quality, quick, workers, out, names, overrides, warm_cache)
    emit(f"quality benchmark: {_count(len(pairs), 'pair')} at --quality {quality}, {workers} at a time with "
         f"{_count(threads, 'thread')} each, {'a warm' if warm_cache else 'each in an empty'} Taichi cache -> {out}")
    rows = {}
    pool = ThreadPoolExecutor(max_workers=workers)
    try:
        running = [pool.submit(run_pair, p, out / p.name, quality, threads, overrides, warm_cache) for p in pairs]
        for done, future in enumerate(as_completed(running), 1):
            row = future.result()
            row["result"] = judge(row, TARGETS[quality])
            rows[row["pair"]] = row
            emit(f"[{done}/{len(pairs)}] {row['pair']:<18s} iou {_num(row.get('iou')):>5s}  mass_error "
                 f"{_num(row.get('mass_error')):>5s}  outside {_num(row.get('mass_outside_target')):>5s}  "
                 f"{row['wall_seconds']:6.1f} s  {row['result']}")
    finally:  # Ctrl-C: pairs not yet started are dropped; running ones got the signal too (same process group)
        pool.shutdown(wait=True, cancel_futures=True)
    rows = [rows[p.name] for p in pairs]
    md = table(rows, quality, workers, threads, command, warm_cache)
    atomic_write(out / "quality.md", lambda fh: fh.write(md.encode()))
    atomic_write(out / "quality.csv", lambda fh: fh.write(_csv_text(rows).encode()))
    emit("")
    emit(md.rstrip("\n"))
    emit(f"written: {out / 'quality.md'}, {out / 'quality.csv'}")
    return rows
