"""The parallel schedule in one launch a pass (mls_mpm/persistent.py) against a launch per step and against the serial
schedule, forward and backward, on the cases of `mls-mpm bench gradient`, alternating runs in one process.

    .venv/bin/python benchmarks/one_launch.py [--case large|small|3d ...] [--repeats 5] [--steps N] [--threads 2]

For each case (mls_mpm/bench/child.py CASES; default: large, small, 3d), a Simulator with sim.schedule = "serial"
and one with "parallel" (--threads lanes); the parallel one runs each pass with a launch per step
(Simulator._persistent_wait held up) and in one launch (the default). Prints ms per step (the least of --repeats
alternating runs, after a compiling one), the speed-up over the serial schedule, and the largest differences: one
launch against a launch per step (their bodies and shares are the same: 0 expected) and the parallel schedule against
the serial one (only the order of the private grids' sums differs), of the final state and of dL/dF_pc.
"""
import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402

from mls_mpm.bench.child import CASES, cpu_model, scene_of  # noqa: E402
from mls_mpm.simulator import Simulator  # noqa: E402

DEFAULT = ["large", "small", "3d"]
LAUNCH_PER_STEP = 10 ** 9  # Simulator._persistent_wait: no one-launch pass


def rel_diff(a, b):
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def measure(name, steps, repeats, threads):
    case = dict(CASES[name], steps=steps or CASES[name]["steps"])
    cfg, x0, loss, controls = scene_of(case, case["steps"])
    serial = Simulator(cfg.replace(schedule="serial", threads=threads), x0, loss=loss)
    parallel = Simulator(cfg.replace(schedule="parallel", threads=threads), x0, loss=loss)
    runs = {"serial": (serial, 0), "parallel, a launch per step": (parallel, LAUNCH_PER_STEP),
            "parallel, one launch a pass": (parallel, 0)}
    results, fwd, bwd = {}, {k: float("inf") for k in runs}, {k: float("inf") for k in runs}
    for r in range(repeats + 1):
        for label, (sim, wait) in runs.items():
            sim._persistent_wait = wait
            t0 = time.perf_counter()
            sim.forward(controls)
            t1 = time.perf_counter()
            g = sim.backward()
            t2 = time.perf_counter()
            if r == 0:  # compiles
                results[label] = (sim.state(case["steps"])["x"], g)
            else:
                fwd[label] = min(fwd[label], (t1 - t0) / case["steps"] * 1e3)
                bwd[label] = min(bwd[label], (t2 - t1) / case["steps"] * 1e3)
    one, per, ser = (results[k] for k in ("parallel, one launch a pass", "parallel, a launch per step", "serial"))
    diffs = (max(rel_diff(one[0], per[0]), rel_diff(one[1], per[1])), rel_diff(per[0], ser[0]), rel_diff(per[1], ser[1]))
    return case, len(x0), fwd, bwd, diffs


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--case", choices=list(CASES), action="append", help="a case (repeatable; default: large, small, 3d)")
    p.add_argument("--repeats", type=int, default=5, help="alternating timed runs; the least is shown")
    p.add_argument("--steps", type=int, default=None, help="steps of each case (default: the case's own)")
    p.add_argument("--threads", type=int, default=2, help="CPU threads, the parallel schedule's lanes")
    args = p.parse_args(argv)
    for name in ("repeats", "steps", "threads"):
        value = getattr(args, name)
        if value is not None and value < 1:
            p.error(f"--{name} {value}: expected an integer >= 1")
    print(f"CPU: {cpu_model()}; {args.threads} threads; ms per step, the least of {args.repeats} alternating runs\n")
    for name in args.case or DEFAULT:
        case, n, fwd, bwd, diffs = measure(name, args.steps, args.repeats, args.threads)
        dim = case.get("dim", 2)
        print(f"{case['dtype']}, {case['n_grid']}^{dim} grid, {n} particles, {case['steps']} steps. Largest relative "
              f"difference: one launch against a launch per step {diffs[0]:.3g}; parallel against serial: final x "
              f"{diffs[1]:.3g}, dL/dF_pc {diffs[2]:.3g}\n")
        print("| schedule | fwd ms/step | bwd ms/step | fwd+bwd | serial / this (fwd+bwd) |\n|---|---|---|---|---|")
        base = fwd["serial"] + bwd["serial"]
        for label in fwd:
            total = fwd[label] + bwd[label]
            print(f"| {label} | {fwd[label]:.3f} | {bwd[label]:.3f} | {total:.3f} | {base / total:.2f} |")
        print()


if __name__ == "__main__":
    main()
