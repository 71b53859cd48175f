"""A whole `mls-mpm` command, timed in a git revision and in the working tree, alternating, in one run.

    .venv/bin/python benchmarks/run_against.py REV [--repeats 2] -- morph INITIAL TARGET [--set KEY=VALUE ...]
    .venv/bin/python benchmarks/run_against.py REV -- run SCENE.toml [--set KEY=VALUE ...]

`mls-mpm bench gradient --against` times the simulator's passes alone; this times what a user waits for (Python's
optimizer and losses between the passes, checkpoints, start-up), which the passes alone do not show. REV is checked
out in a temporary git worktree (mls_mpm.bench.against.worktree, removed afterwards). Each repeat runs the command
once in REV's tree and once in the working tree, each process importing its own tree's mls_mpm (PYTHONPATH and
working folder), with `--out` a fresh folder, `--no-render --quiet` added; a warm-up run of each first fills Taichi's
offline cache. Give the command a fixed amount of work (`--set optimize.max_seconds=0 --set optimize.iterations=N`),
or a time-bound run measures its budget. Prints, per run, the wall seconds of the process and what its summary.json
says (wall_seconds, iterations, final loss, iou), then the least wall time of each tree and their ratio.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from mls_mpm.bench.against import sigterm_unwinds, worktree  # noqa: E402  (after the path)


def run_once(tree, command, out):
    """The mls-mpm command in `tree`, its output in `out`; (wall seconds, summary dict)."""
    cmd = [sys.executable, "-m", "mls_mpm.cli", *command, "--out", str(out), "--no-render", "--quiet"]
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(tree)}
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode:
        sys.exit(f"run_against: {' '.join(command)} failed in {tree} (exit {res.returncode}): {res.stderr[-1500:]}")
    return wall, json.loads((Path(out) / "summary.json").read_text())


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 usage="%(prog)s REV [--repeats K] -- run|morph ... (the mls-mpm command)")
    ap.add_argument("rev", help="git revision to compare the working tree with, e.g. HEAD~1")
    ap.add_argument("--repeats", type=int, default=2, help="measured runs of each tree after the warm-up (default 2)")
    argv = sys.argv[1:]  # the mls-mpm command after "--" is split off by hand: argparse would read its options
    cut = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:cut])
    command = argv[cut + 1:]
    if not command or command[0] not in ("run", "morph"):
        ap.error("expected -- then an `mls-mpm run` or `mls-mpm morph` command")
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: expected at least 1")
    walls = {"old": [], "new": []}
    with sigterm_unwinds(), worktree(args.rev) as old, tempfile.TemporaryDirectory(prefix="run_against_") as tmp:
        trees = {"old": old, "new": ROOT}
        for i in range(args.repeats + 1):
            for name, tree in trees.items():
                wall, s = run_once(tree, command, Path(tmp) / f"{name}{i}")
                loss = s["loss_final"]
                print(f"{'warm-up' if i == 0 else f'repeat {i}'} {name}: {wall:.1f} s (summary {s['wall_seconds']:.1f} "
                      f"s), {s['iterations']} iterations, loss {loss:.6e}, iou {s.get('iou')}", flush=True)
                if i:
                    walls[name].append(wall)
    old_s, new_s = min(walls["old"]), min(walls["new"])
    print(f"least wall: {args.rev} {old_s:.1f} s, working tree {new_s:.1f} s, speed-up {old_s / new_s:.2f}x")


if __name__ == "__main__":
    main()
