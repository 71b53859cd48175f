"""Where a 2D step's time goes: each loop of the serial schedule's forward and reverse step, timed on its own.

    .venv/bin/python benchmarks/loop_profile.py [--case large|small ...] [--repeats 5] [--steps N]

For each case of `mls-mpm bench gradient` (mls_mpm/bench/child.py CASES; default: the two 2D ones), one forward and
backward pass of the real simulator, then each loop of a step (mls_mpm/step.py step_loops, adjoint/step.py
step_loops_reverse) in a serial kernel of its own that runs it for every step in one launch, as the serial schedule
does. Prints a Markdown table of ms per step (the least of --repeats launches after a compiling one) with the whole
forward() and backward() beside them, and the CPU model.

Only the times mean something: the loops rerun on the stored steps without the rest of their pass (grid masses
accumulate, adjoints are not zeroed between runs), so the values they leave are not a simulation's. The forward
loops run first and the forward pass is run again before the reverse loops.
"""
import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import taichi as ti  # noqa: E402

from adjoint.step import grid_node_reverse, particle_adjoint  # noqa: E402
from mls_mpm.bench.child import CASES, cpu_model, scene_of  # noqa: E402
from mls_mpm.simulator import Simulator  # noqa: E402
from mls_mpm.step import grid_node  # noqa: E402
from mls_mpm.transfer import check_particle, g2p_particle, p2g_particle, particle_G  # noqa: E402

CASES_2D = [name for name, case in CASES.items() if case.get("dim", 2) == 2]


@ti.kernel
def p2g_loop(s: ti.template(), n: ti.i32):
    """The stress, P2G and check of steps 0..n-1 (step_loops' first loop, lanes = 0)."""
    ti.loop_config(serialize=True)
    for f in range(n):
        for p in range(s.n_particles):
            check_particle(s, f, p, p2g_particle(s, f, p, 0, particle_G(s, f, p)))


@ti.kernel
def grid_loop(s: ti.template(), n: ti.i32):
    ti.loop_config(serialize=True)
    for f in range(n):
        for I in ti.grouped(ti.ndrange(*s.grid_shape)):
            grid_node(s, f, I)


@ti.kernel
def g2p_loop(s: ti.template(), n: ti.i32):
    ti.loop_config(serialize=True)
    for f in range(n):
        for p in range(s.n_particles):
            g2p_particle(s, f, p)


@ti.kernel
def grid_reverse_loop(s: ti.template(), a: ti.template(), n: ti.i32):
    ti.loop_config(serialize=True)
    for k in range(n):
        for I in ti.grouped(ti.ndrange(*s.grid_shape)):
            grid_node_reverse(s, a, n - 1 - k, I, 0, n)


@ti.kernel
def particle_reverse_loop(s: ti.template(), a: ti.template(), n: ti.i32):
    """The reverse pass's particle loop: reverse P2G of step f and reverse G2P of step f - 1 (particle_adjoint)."""
    ti.loop_config(serialize=True)
    for k in range(n):
        for p in range(s.n_particles):
            particle_adjoint(s, a, n - 1 - k, p, 0, 0, n)


def best_ms(run, steps, repeats):
    """ms per step of run(): the least of `repeats` calls after one that compiles."""
    run()
    ti.sync()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        ti.sync()
        best = min(best, time.perf_counter() - t0)
    return best / steps * 1e3


def profile(name, repeats, steps=None):
    """[(row label, ms per step)] of case `name` (over `steps` steps, default the case's): forward(), backward(),
    then the loops of each."""
    case = dict(CASES[name], schedule="serial")
    steps = steps or case["steps"]
    cfg, x0, loss, controls = scene_of(case, steps)
    sim = Simulator(cfg, x0, loss=loss)
    s = sim.fields
    rows = [("forward() (whole pass)", best_ms(lambda: sim.forward(controls), steps, repeats))]
    sim.forward(controls)
    sim.backward()
    a = sim._adjoint_state()
    rows.append(("backward() (whole pass)", best_ms(sim.backward, steps, repeats)))
    for label, kernel in [("forward: stress + P2G + check", p2g_loop), ("forward: grid", grid_loop),
                          ("forward: G2P", g2p_loop)]:
        rows.append((label, best_ms(lambda k=kernel: k(s, steps), steps, repeats)))
    sim.forward(controls)  # the stored steps again, for the reverse loops
    for label, kernel in [("reverse: grid", grid_reverse_loop),
                          ("reverse: stress + P2G + check, G2P of the step before", particle_reverse_loop)]:
        rows.append((label, best_ms(lambda k=kernel: k(s, a, steps), steps, repeats)))
    return case, steps, rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", action="append", choices=CASES_2D, help="a 2D case of bench gradient (repeatable; "
                    "default: all of them)")
    ap.add_argument("--repeats", type=int, default=5, help="timed launches of each loop; the least is shown")
    ap.add_argument("--steps", type=int, help="steps of each case (default: the case's own, 200)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error(f"--repeats {args.repeats}: expected an integer >= 1")
    if args.steps is not None and args.steps < 1:
        ap.error(f"--steps {args.steps}: expected an integer >= 1")
    print(f"CPU: {cpu_model()}; serial schedule (one thread); ms per step, the least of {args.repeats} launches")
    for name in args.case or CASES_2D:
        case, steps, rows = profile(name, args.repeats, args.steps)
        print()
        print(f"{case['dtype']}, {case['n_grid']}^2 grid, {case['particles']} particles, {steps} steps")
        print()
        print("| loop | ms/step |")
        print("|---|---|")
        for label, ms in rows:
            print(f"| {label} | {ms:.3f} |", flush=True)


if __name__ == "__main__":
    main()
