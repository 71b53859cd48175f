"""GPU helpers for benchmarks/gpu.sh: compile every benchmark case at once, and time cases a GPU is made for.

    python3 benchmarks/gpu_cases.py compile [--arch gpu] [--quick]   # all children at once: fills Taichi's cache
    python3 benchmarks/gpu_cases.py scale [--arch gpu] [--quick]     # the SCALE cases, one after another
    python3 benchmarks/gpu_cases.py profile [--arch gpu] [--quick]   # Taichi's kernel profiler on PROFILED

`compile` runs one child (mls_mpm.bench.child.run_child: a fresh process, a warm-up pass, then a timed one) for
every case of `mls-mpm bench gradient` (manual and Tape) and of SCALE (manual) at the same time, so that the
compiles, which use one CPU core each, overlap; the sequential timings that follow then find every kernel in
Taichi's offline cache. Its figures are not reported (the children ran side by side).

`scale` times forward and manual backward of SCALE, sizes where the CPU benchmarks stop: one child each, after
`compile`. It prints a Markdown table with the device's name.

`profile` runs PROFILED with Taichi's kernel profiler: where a forward's and a backward's wall time goes.
"""
import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mls_mpm.bench.child import CASES, case_label, case_steps, run_child  # noqa: E402
from mls_mpm.bench.gradient import measured_on  # noqa: E402

# f32, the benchmark's disk and ball (mls_mpm.bench.child.scene_of) at grid sizes a GPU is made for, dt = 1e-4 as
# there: 256^2 and 128^3 are within its CFL limit (bench scaling runs n_grid 256 at that dt)
# (random particle order, as in bench gradient), and each again with the particles numbered cell by cell (order)
SCALE = {
    "2d 256": dict(dtype="f32", n_grid=256, particles=262144, steps=200),
    "3d 128": dict(dim=3, dtype="f32", n_grid=128, particles=1048576, steps=30),
}
QUICK = {  # a dry run of the script on a CPU in a minute or two
    "2d 256": dict(dtype="f32", n_grid=64, particles=8192, steps=20),
    "3d 128": dict(dim=3, dtype="f32", n_grid=16, particles=4096, steps=4),
}
for _cases in (SCALE, QUICK):
    _cases.update({f"{k} by cell": dict(v, order="cell") for k, v in list(_cases.items())})
PROFILED = "3d 128"  # the case `profile` runs


def jobs(arch, quick):
    """(label, case, path, steps) of every child `compile` starts."""
    out = []
    for name, case in CASES.items():
        for path in ("manual", "tape"):
            out.append((name, dict(case, arch=arch), path, case_steps(case, quick)))
    for name, case in (QUICK if quick else SCALE).items():
        if "order" not in case:  # the same kernels as the case it reorders
            out.append((name, dict(case, arch=arch), "manual", case["steps"]))
    if quick:  # the CPU dry run: the 2D cases only (the 3D ones compile for minutes on two cores)
        out = [j for j in out if j[1].get("dim", 2) == 2 or j[0] in QUICK]
    return out


def compile_all(arch, quick):
    def one(job):
        name, case, path, steps = job
        t = time.perf_counter()
        try:
            run_child(case, path, steps)
            return f"{name} {path}: compiled and ran in {time.perf_counter() - t:.0f} s"
        except RuntimeError as e:
            return f"{name} {path}: FAILED after {time.perf_counter() - t:.0f} s: {e}"

    todo = jobs(arch, quick)
    with ThreadPoolExecutor(len(todo)) as pool:
        for line in pool.map(one, todo):
            print(line, flush=True)


def scale(arch, quick):
    cases = QUICK if quick else SCALE
    rows = [(case, run_child(dict(case, arch=arch), "manual", case["steps"])) for case in cases.values()]
    print(f"{measured_on(rows[0][1]['backend'])}. One run each after a warm-up pass in the same process.\n")
    print("| case | fwd ms/step | particle-steps/s | manual bwd ms/step | bwd / fwd |")
    print("|---|---|---|---|---|")
    for case, r in rows:
        fwd, bwd = r["forward_ms"], r["backward_ms"]
        print(f"| {case_label(case, case['steps'])} | {fwd:.3f} | {case['particles'] / fwd / 1e3:.1f} M | {bwd:.3f} | "
              f"{bwd / fwd:.2f} |")


def profile(arch, quick):
    """Taichi's kernel profiler over one forward and one manual backward of PROFILED (after a warm-up pass): each
    kernel's launches and time, against the wall time of the call; what is not kernel time is launches and host work
    (the controls checked and uploaded, the gradient copied back). Run in a process of its own (it starts Taichi with
    the profiler on)."""
    os.environ["TI_KERNEL_PROFILER"] = "1"
    import taichi as ti

    from mls_mpm.bench.child import scene_of
    from mls_mpm.simulator import Simulator

    case = dict((QUICK if quick else SCALE)[PROFILED], arch=arch)
    cfg, x0, loss, controls = scene_of(case, case["steps"])
    sim = Simulator(cfg, x0, loss=loss)
    sim.forward(controls)
    sim.backward()
    print(f"Kernel profile: {case_label(case, case['steps'])}, one call each after a warm-up pass. A step's loops "
          "are the offloaded tasks of `substep` (step.step_loops, in order: with lanes, as on a CPU, stresses, "
          "P2G, grid, G2P; without, as on a GPU, P2G with the stress, grid, G2P), of `substep_reverse` the reverse "
          "loops (adjoint.step).\n")
    for name, call in (("forward", lambda: sim.forward(controls)), ("backward", sim.backward)):
        ti.sync()
        ti.profiler.clear_kernel_profiler_info()
        t = time.perf_counter()
        call()
        ti.sync()
        wall = time.perf_counter() - t
        kernels = ti.profiler.get_kernel_profiler_total_time()
        print(f"{name}: wall {wall / case['steps'] * 1e3:.3f} ms/step, kernels {kernels / case['steps'] * 1e3:.3f} "
              f"ms/step ({kernels / wall:.0%} of the wall time)")
        ti.profiler.print_kernel_profiler_info("count")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["compile", "scale", "profile"])
    p.add_argument("--arch", default="gpu", choices=["cpu", "gpu", "cuda", "vulkan"])
    p.add_argument("--quick", action="store_true", help="small sizes, 2D bench cases only: a dry run on a CPU")
    args = p.parse_args(argv)
    {"compile": compile_all, "scale": scale, "profile": profile}[args.what](args.arch, args.quick)


if __name__ == "__main__":
    main()
