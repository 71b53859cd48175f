"""How much of a 3D step is the grid: the same particles simulated on grids of different sizes.

    .venv/bin/python benchmarks/grid_cost.py [--particles 1192] [--grids 24,32,48] [--rounds 2] [--steps 100]

A ball of radius 0.2 (domain units) of --particles particles, the 3D morph's material and settings (f64, dt 1/120,
E = 90000 dx^2, nu 0.3, density 40, drag 0.5, a control every 10 steps: mls_mpm/morph.py) and a mass loss, run on each
grid of --grids in a process of its own (schedule `auto`, 2 threads), the grids alternating over --rounds rounds.
The particle loops do the same work on every grid (4^3 nodes a particle); the grid loops (the grid operations, the
threads' private grids summed and cleared, their reverse) visit every node of the n^3 grid each step. So the time
that grows with n^3 at a fixed particle count is the grid's, and its slope per node times 32^3 is what the grid loops
cost the 3D default's grid. Prints ms per step, forward and backward (least over the rounds), and that slope.
"""
import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

CHILD = """
import json, sys, time
import numpy as np
from mls_mpm.bench.child import _ball_mass
from mls_mpm.config import SimConfig
from mls_mpm.losses import MassLoss
from mls_mpm.simulator import Simulator

n, P, steps = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
rng = np.random.default_rng(0)
cfg = SimConfig(dim=3, n_grid=n, steps=steps, stride=10, dtype="f64", threads=2, schedule="auto", arch="cpu",
                dt=1 / 120, E=90000.0 / n ** 2, nu=0.3, density=40.0, gamma=0.5, gravity=(0.0,) * 3,
                particles_per_cell=1)
u = rng.standard_normal((P, 3))
x0 = 0.5 + 0.2 * u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0, 1, (P, 1)) ** (1 / 3)
sim = Simulator(cfg, x0, loss=MassLoss([_ball_mass(n, 0.5 + np.array([0.02, 0.0, 0.0]), 0.2, P * cfg.m_p)]))
controls = 0.01 * rng.standard_normal((cfg.n_controls, P, 3, 3))
sim.forward(controls)
sim.backward()  # compiles every kernel
fwd = bwd = float("inf")
for _ in range(5):
    t0 = time.perf_counter()
    sim.forward(controls)
    t1 = time.perf_counter()
    sim.backward()
    t2 = time.perf_counter()
    fwd, bwd = min(fwd, t1 - t0), min(bwd, t2 - t1)
print(json.dumps({"fwd": fwd / steps * 1e3, "bwd": bwd / steps * 1e3}))
"""


def main():
    from mls_mpm.bench.child import cpu_model

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=1192, help="particles in the ball (default: 1192, the 3D "
                    "suite's shrink_ball at 32^3)")
    ap.add_argument("--grids", default="24,32,48", help="n_grid values, comma-separated (default: 24,32,48)")
    ap.add_argument("--rounds", type=int, default=2, help="rounds over the grids, alternating (default: 2)")
    ap.add_argument("--steps", type=int, default=100, help="steps a pass (default: 100, the morph's least)")
    args = ap.parse_args()
    grids = [int(g) for g in args.grids.split(",")]
    best = {n: {"fwd": float("inf"), "bwd": float("inf")} for n in grids}
    for _ in range(args.rounds):
        for n in grids:
            out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(args.particles), str(args.steps)],
                                 capture_output=True, text=True, cwd=ROOT, check=True).stdout
            got = json.loads(out.strip().splitlines()[-1])
            best[n] = {k: min(best[n][k], got[k]) for k in got}
    print(f"{args.particles} particles, {args.steps} steps, f64, 2 threads; least of {args.rounds} rounds; "
          f"CPU: {cpu_model()}\n")
    print("| n_grid | nodes | fwd ms/step | bwd ms/step | fwd + bwd |")
    print("|---|---|---|---|---|")
    for n in grids:
        b = best[n]
        print(f"| {n} | {n ** 3:,} | {b['fwd']:.3f} | {b['bwd']:.3f} | {b['fwd'] + b['bwd']:.3f} |")
    lo, hi = min(grids), max(grids)
    slope = ((best[hi]["fwd"] + best[hi]["bwd"]) - (best[lo]["fwd"] + best[lo]["bwd"])) / (hi ** 3 - lo ** 3)
    total32 = best[32]["fwd"] + best[32]["bwd"] if 32 in best else None
    print(f"\nslope {slope * 1e6:.1f} ns per node and step (fwd + bwd, {lo}^3 to {hi}^3): {slope * 32 ** 3:.3f} ms "
          f"a step at 32^3" + (f", {slope * 32 ** 3 / total32:.0%} of its {total32:.3f}" if total32 else ""))


if __name__ == "__main__":
    main()
