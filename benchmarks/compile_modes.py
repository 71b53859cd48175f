"""Compile time and run time of MLS_MPM_COMPILE=optimized against =fast (the default): the figures behind
`mls_mpm.config.compile_mode`.

    .venv/bin/python benchmarks/compile_modes.py [--quick] [--rounds R]

Each case (`mls_mpm.bench.child.CASES`: the 2D thesis size, the 2D 64^2 / 8k case, the 3D 32^3 / 16k case) is
built in a fresh process with an empty Taichi offline cache of its own, so every kernel compiles: the seconds of
its first forward and of its first manual backward are the compile times (plus one run, negligible beside them),
then the best of 3 forward and backward passes gives ms per step. The two modes alternate, R rounds; the table
shows the median of each figure and the ratio fast / optimized, with the CPU model.

Each child also hashes its results (the loss, the final state, dL/dF_pc and dL/dx0 of its first pass): the column
"results" says whether every child of a case, in either mode, got the same bits, and the script exits 1 where they
differ. This is where the 3D optimized build is checked against the default fast one (a 3D optimized compile takes
2-3 minutes, too long for the test suite; tests/test_runtime.py compares the modes in 2D).
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mls_mpm.bench.child import CASES, THREADS, case_label, cpu_model  # noqa: E402

MODES = ("optimized", "fast")
CHILD = r"""
import hashlib, json, sys, time
import numpy as np
from mls_mpm.bench.child import CASES, scene_of
from mls_mpm.simulator import Simulator

case = dict(CASES[sys.argv[1]])
steps = int(sys.argv[2])
cfg, x0, loss, controls = scene_of(case, steps)
sim = Simulator(cfg, x0, loss=loss)
t0 = time.perf_counter()
loss_value = sim.forward(controls)
t1 = time.perf_counter()
grad = sim.backward()
t2 = time.perf_counter()
digest = hashlib.sha256(np.float64(loss_value).tobytes())
for key, value in sorted(sim.state(steps).items()):
    digest.update(key.encode() + np.ascontiguousarray(value).tobytes())
digest.update(np.ascontiguousarray(grad).tobytes() + np.ascontiguousarray(sim.grad_x0).tobytes())
fwd, bwd = [], []
for _ in range(3):
    a = time.perf_counter()
    sim.forward(controls)
    b = time.perf_counter()
    sim.backward()
    c = time.perf_counter()
    fwd.append((b - a) / steps * 1e3)
    bwd.append((c - b) / steps * 1e3)
print(json.dumps({"compile_forward_s": t1 - t0, "compile_backward_s": t2 - t1, "forward_ms": min(fwd),
                  "backward_ms": min(bwd), "results": digest.hexdigest()}))
"""
FIGURES = ("compile_forward_s", "compile_backward_s", "forward_ms", "backward_ms")


def measure(case, steps, mode):
    """One cold child of `case` compiled in `mode`: its FIGURES."""
    with tempfile.TemporaryDirectory(prefix="mls-mpm-compile-") as cache:
        env = {**os.environ, "MLS_MPM_COMPILE": mode, "TI_OFFLINE_CACHE_FILE_PATH": cache, "TI_LOG_LEVEL": "error"}
        res = subprocess.run([sys.executable, "-c", CHILD, case, str(steps)], capture_output=True, text=True, env=env)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode or not lines:
        raise SystemExit(f"compile_modes: the {case} child ({mode}) failed:\n{res.stderr[-2000:]}")
    return json.loads(lines[-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the 2D thesis size only, one round")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds per case (medians are reported)")
    args = ap.parse_args(argv)
    rounds = 1 if args.quick else max(1, args.rounds)
    cases = [("small", 100)] if args.quick else [("small", 100), ("large", 100), ("3d", 30)]
    print(f"CPU: {cpu_model()}; Taichi on {THREADS} threads; {rounds} round(s), medians; a cold Taichi cache per "
          "process", flush=True)
    print("\n| case | mode | compile forward s | compile backward s | forward ms/step | backward ms/step | results |")
    print("|---|---|---|---|---|---|---|")
    differ = []
    for name, steps in cases:
        runs = {mode: [] for mode in MODES}
        for _ in range(rounds):
            for mode in MODES:
                runs[mode].append(measure(name, steps, mode))
        med = {mode: {k: statistics.median(r[k] for r in runs[mode]) for k in FIGURES} for mode in MODES}
        label = case_label(CASES[name], steps)
        for mode in MODES:
            m = med[mode]
            print(f"| {label} | {mode} | {m['compile_forward_s']:.1f} | {m['compile_backward_s']:.1f} | "
                  f"{m['forward_ms']:.3f} | {m['backward_ms']:.3f} | {runs[mode][0]['results'][:12]} |")
        ratio = {k: med["fast"][k] / med["optimized"][k] for k in FIGURES}
        same = len({r["results"] for mode in MODES for r in runs[mode]}) == 1
        if not same:
            differ.append(label)
        print(f"| {label} | fast / optimized | {ratio['compile_forward_s']:.2f}x | {ratio['compile_backward_s']:.2f}x "
              f"| {ratio['forward_ms']:.2f}x | {ratio['backward_ms']:.2f}x | "
              f"{'identical' if same else 'DIFFER'} |", flush=True)
    if differ:
        print(f"\nresults differ between the compile modes (or between runs): {', '.join(differ)}")
        return 1
    print("\nresults: identical to the bit in both modes, every case and round")
    return 0


if __name__ == "__main__":
    sys.exit(main())
