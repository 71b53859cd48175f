"""What a parallel loop's dispatch costs on this machine: the same G2P loop (the real step body) launched serially, as a
parallel range-for, pinned to one CPU, and run many times inside one parallel launch.

    .venv/bin/python benchmarks/dispatch_cost.py [--threads 1] [--launches 100] [--repeats 5]

On the f32 64^2 / 8k case of `mls-mpm bench gradient` (mls_mpm/bench/child.py CASES["large"]), one forward pass of
the real simulator, then G2P (mls_mpm/transfer.py g2p_particle) of the stored steps, one step a launch, in kernels of
its own:
- serial: a serialized loop, run by the launching (main) thread, as the serial schedule runs every loop;
- parallel: a range-for (mls_mpm/transfer.py g2p), run by Taichi's worker threads (--threads of them), as the
  parallel schedule runs it;
- parallel, pinned: the same with every thread of the process pinned to the main thread's CPU
  (os.sched_setaffinity), so that no other CPU has to be woken for it;
- one launch: a single parallel launch whose one item runs the loop --launches times: the loop body's own speed
  in a worker thread, without dispatches;
- empty: a parallel loop with nothing in it.
Prints ms per launch (per pass for "one launch"), the least of --repeats rounds of --launches launches, and the CPU.
The difference between "parallel" and "one launch" is what each dispatch costs: waking the worker's CPU and
refilling its caches, large on a virtual machine whose idle virtual CPUs halt (BENCHMARKS.md, "Issue 14").
"""
import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import taichi as ti  # noqa: E402

from mls_mpm.bench.child import CASES, cpu_model, scene_of  # noqa: E402
from mls_mpm.simulator import Simulator  # noqa: E402
from mls_mpm.transfer import g2p, g2p_particle  # noqa: E402


@ti.kernel
def g2p_serial(s: ti.template(), f: ti.i32):
    ti.loop_config(serialize=True)
    for p in range(s.n_particles):
        g2p_particle(s, f, p)


@ti.kernel
def g2p_passes(s: ti.template(), passes: ti.i32):
    """`passes` G2P passes over steps 0, 1, ... in one parallel launch of one item: one worker thread runs them all."""
    for _ in range(1):
        for k in range(passes):
            for p in range(s.n_particles):
                g2p_particle(s, k % (s.steps - 1), p)


@ti.kernel
def empty_parallel(s: ti.template(), f: ti.i32):
    for p in range(s.n_particles):
        pass


def per_launch(kernel, s, launches, repeats):
    """ms per launch of kernel(s, f) over steps f = 0, 1, ...: the least of `repeats` rounds of `launches`."""
    kernel(s, 0)
    ti.sync()
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for f in range(launches):
            kernel(s, f % (s.steps - 1))
        ti.sync()
        best = min(best, (time.perf_counter() - t) / launches * 1e3)
    return best


def pin_all(cpus):
    """Set the CPU affinity of every thread of this process (the main thread and Taichi's workers)."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:  # a thread that ended meanwhile
            pass


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=1, help="Taichi's CPU threads (sim.threads)")
    p.add_argument("--launches", type=int, default=100, help="launches a round (and passes of 'one launch')")
    p.add_argument("--repeats", type=int, default=5, help="rounds; the least is shown")
    args = p.parse_args(argv)
    for name in ("threads", "launches", "repeats"):
        if getattr(args, name) < 1:
            p.error(f"--{name} {getattr(args, name)}: expected an integer >= 1")
    case = dict(CASES["large"], schedule="parallel")
    import mls_mpm.bench.child as child

    child.THREADS = args.threads  # scene_of's sim.threads on a CPU
    cfg, x0, loss, controls = scene_of(case, case["steps"])
    sim = Simulator(cfg, x0, loss=loss)
    sim.forward(controls)
    s = sim.fields
    all_cpus = os.sched_getaffinity(0)
    main_cpu = os.sched_getaffinity(0) if len(all_cpus) == 1 else {min(all_cpus)}
    rows = [("serial loop, run by the main thread", per_launch(g2p_serial, s, args.launches, args.repeats)),
            (f"parallel loop, {args.threads} worker thread(s)", per_launch(g2p, s, args.launches,
                                                                            args.repeats))]
    pin_all(main_cpu)
    try:
        rows.append(("parallel loop, every thread pinned to one CPU",
                     per_launch(g2p, s, args.launches, args.repeats)))
    finally:
        pin_all(all_cpus)
    g2p_passes(s, 1)
    ti.sync()
    best = float("inf")
    for _ in range(args.repeats):
        t = time.perf_counter()
        g2p_passes(s, args.launches)
        ti.sync()
        best = min(best, (time.perf_counter() - t) / args.launches * 1e3)
    rows.append((f"one parallel launch running {args.launches} passes in one worker, per pass", best))
    rows.append(("empty parallel loop", per_launch(empty_parallel, s, args.launches, args.repeats)))
    print(f"CPU: {cpu_model()} ({len(all_cpus)} CPUs usable); G2P of {len(x0)} particles, f32, "
          f"{cfg.n_grid}^2 grid; ms per launch, the least of {args.repeats} rounds of {args.launches}\n")
    print("| loop | ms |\n|---|---|")
    for label, ms in rows:
        print(f"| {label} | {ms:.4f} |")


if __name__ == "__main__":
    main()
