"""Serial against parallel stepping on this machine: the figures behind `sim.schedule = "auto"`.

    .venv/bin/python benchmarks/schedules.py [--quick] [--rounds R]

Each case runs forward and manual backward (`mls_mpm.bench.child.measure`, a fresh process each, compile time
excluded by a warm-up pass) once with `schedule = "serial"` (all steps in one launch, one thread) and once with
`"parallel"` (2 threads with private scatter grids, each pass in one launch: mls_mpm/persistent.py; the worker
threads pinned one to each CPU where the 2 threads are the process's CPUs: mls_mpm/affinity.py), R rounds
alternating, and prints a Markdown table of the medians in ms per step with the CPU model: which schedule is
faster where.
"""
import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mls_mpm.bench.child import CASES, run_child  # noqa: E402
from mls_mpm.bench.quality import cpu_model  # noqa: E402

STEPS = 110  # a morph's typical window (mls-mpm morph chooses 100-400 steps)
CASES_2D = [(32, 300), (32, 600), (32, 1245), (64, 1600), (64, 4000), (64, 8000), (64, 16000), (128, 32000),
            (128, 64000)]


def cases(quick):
    picked = CASES_2D[3:6:2] if quick else CASES_2D
    out = [(f"2D f64, {n}^2, {p} particles", dict(dtype="f64", n_grid=n, particles=p, steps=STEPS), STEPS)
           for n, p in picked]
    if not quick:
        out.append(("3D f64, the 3D successor's window (32^3, 17,157 particles)",
                    dict(CASES["3d window"], dtype="f64"), CASES["3d window"]["steps"]))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two 2D cases, one round")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds per case (medians are reported)")
    args = ap.parse_args(argv)
    rounds = 1 if args.quick else max(1, args.rounds)
    print(f"CPU: {cpu_model()}, 2 threads for the parallel schedule; {rounds} round(s), medians; ms per step")
    print()
    print("| case | serial fwd | serial bwd | parallel fwd | parallel bwd | faster (fwd + bwd) |")
    print("|---|---|---|---|---|---|")
    for name, case, steps in cases(args.quick):
        got = {"serial": [], "parallel": []}
        for _ in range(rounds):
            for schedule in got:
                r = run_child(dict(case, schedule=schedule), "manual", steps)
                got[schedule].append((r["forward_ms"], r["backward_ms"]))
        med = {k: [statistics.median(x[i] for x in v) for i in (0, 1)] for k, v in got.items()}
        s, p = sum(med["serial"]), sum(med["parallel"])
        faster = f"serial, {p / s:.2f}x" if s < p else f"parallel, {s / p:.2f}x"
        print(f"| {name} | {med['serial'][0]:.3f} | {med['serial'][1]:.3f} | {med['parallel'][0]:.3f} | "
              f"{med['parallel'][1]:.3f} | {faster} |", flush=True)


if __name__ == "__main__":
    main()
