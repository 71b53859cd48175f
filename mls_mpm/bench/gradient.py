"""`mls-mpm bench gradient`: forward, manual backward and ti.ad.Tape speed and peak memory.

Each measurement runs in its own process (child.py), and every ratio is taken between figures measured in
the same invocation. Compile time is excluded by a warm-up pass, and the compiler's memory by running each
child twice (the first fills Taichi's offline cache).
"""
import os
import subprocess

from .child import (CASES, THREADS, TINY_PARTICLES, TINY_STEPS, backend_here, case_label, case_steps, cpu_model,
                    run_child)
from ..config import compile_mode
from .output import writable_file

FAST_COMPILE_NOTE = " (MLS_MPM_COMPILE=fast: Taichi's IR optimizations off, except for the Tape)"
MEMORY_CPU = (f"peak RSS of the path's process minus that of the same path at {TINY_PARTICLES} particles and "
              f"{TINY_STEPS} steps (Python, Taichi and the compiled kernels), i.e. the memory the data needs")


def bench_gradient(quick=False, emit=print, arch="cpu", out=None, dims=(2, 3), repeats=1):
    """Print the gradient benchmark as a markdown table (and return its rows); out: also write it there.
    dims: the dimensions whose cases run (CASES, 2D and 3D). repeats: measured runs of each child after its
    warm-up; each figure is the least over them (a run the rest of the machine slowed least).

    A file `out` that could not be written is refused before anything is measured."""
    if out:
        writable_file(out)
    backend = backend_here(arch)
    lines = []

    def say(text):
        lines.append(text)
        emit(text)

    def warm(*args, **kwargs):
        """A child run 1 + repeats times, the last `repeats` measured (the least of each figure): the first fills
        Taichi's offline cache, so that no peak RSS holds the compiler's memory (the sizes are compile-time
        constants: the tiny runs compile kernels of their own). On a GPU, where no memory is measured, `repeats`
        times (each child still compiles and runs a warm-up pass before it measures)."""
        if backend == "cpu":  # a GPU run measures no memory: the child's own warm-up pass excludes compile time
            run_child(*args, **kwargs)
        runs = [run_child(*args, **kwargs) for _ in range(repeats)]
        return {k: min(r[k] for r in runs) if k.endswith(("_ms", "_mib")) else runs[-1][k] for k in runs[-1]}

    rows = []
    for name, case in CASES.items():
        if case.get("dim", 2) not in dims:
            continue
        case = dict(case, arch=arch)
        steps = case_steps(case, quick)
        man = warm(case, "manual", steps)
        tape = warm(case, "tape", steps)  # in 3D its child initialises Taichi for the Tape (runtime.ensure)
        if backend == "cpu":  # on a GPU the fields live in device memory: host RSS says nothing of them
            man["peak_mib"] -= warm(case, "manual", steps, tiny=True)["peak_mib"]
            tape["peak_mib"] -= warm(case, "tape", steps, tiny=True)["peak_mib"]
        rows.append((name, case, steps, man, tape))
    memory = (MEMORY_CPU if backend == "cpu" else
              "not measured (the fields live in device memory; the estimate of the preallocated fields is in "
              "the scaling table)")
    least = (f" Each figure: the least over {repeats} runs{' after a warm-up run' if backend == 'cpu' else ''}."
             if repeats > 1 else "")
    say(f"{measured_on(backend)}. Memory: {memory}.{least}\n")
    say("| case | fwd ms/step | particle-steps/s | manual bwd ms/step | bwd / fwd | Tape fwd+bwd ms/step | "
        "Tape / manual (fwd+bwd) | manual MiB | Tape MiB | manual / Tape memory |")
    say("|---|---|---|---|---|---|---|---|---|---|")
    for name, case, steps, man, tape in rows:
        ran = {man["backend"], tape["backend"]}
        if ran != {backend}:
            raise RuntimeError(f"benchmark children ran on {', '.join(sorted(ran))}, not {backend}")
        fwd, bwd = man["forward_ms"], man["backward_ms"]
        m_man = man["peak_mib"]
        tp, m_tape = tape["tape_ms"], tape["peak_mib"]
        mem = f"{m_man:.0f} | {m_tape:.0f} | {m_man / m_tape:.2f}" if backend == "cpu" else "- | - | -"
        taped = f"{tp:.3f} | {tp / (fwd + bwd):.2f}"
        say(f"| {case_label(case, steps)} | {fwd:.3f} | {case['particles'] / fwd * 1e3 / 1e6:.2f} M | {bwd:.3f} | "
            f"{bwd / fwd:.2f} | {taped} | {mem} |")
    speed = {name: case["particles"] / man["forward_ms"] for name, case, _, man, _ in rows}  # particle-steps/ms
    if "large" in speed and "3d" in speed:
        say(f"\n3D forward particle-steps/s (f32, 32^3) / 2D (f32, 64^2), this run: {speed['3d'] / speed['large']:.2f} "
            "(target >= 0.25: the 3D stencil is 4x wider).")
    for name, case, steps, man, _ in rows:
        if case.get("window"):
            say(f"One {steps}-step window of the 3D successor's settings ({case['particles']} particles, 32^3): "
                f"forward + manual backward {(man['forward_ms'] + man['backward_ms']) * steps / 1e3:.2f} s "
                "(target <= 1 s).")
    if out:
        from ..checkpoint import atomic_write

        atomic_write(out, lambda fh: fh.write(("\n".join(lines) + "\n").encode()))
    return rows


def measured_on(backend):
    """What the children ran on, said beside every figure: "Taichi CPU, 2 threads; CPU: model (n logical CPUs)",
    on a GPU "Taichi cuda (the GPU's name); CPU: ..."."""
    taichi = f"Taichi CPU, {THREADS} threads" if backend == "cpu" else f"Taichi {backend} ({_device_name(backend)})"
    if backend == "cpu" and compile_mode() == "fast":
        taichi += FAST_COMPILE_NOTE
    return f"{taichi}; CPU: {cpu_model()} ({os.cpu_count()} logical CPUs)"


def _device_name(backend):
    """The GPU's name from nvidia-smi (CUDA), or the backend's name where that is not to be had."""
    if backend == "cuda":
        try:
            res = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                                 text=True, timeout=30)
            if res.returncode == 0 and res.stdout.strip():
                return res.stdout.strip().splitlines()[0]
        except (OSError, subprocess.TimeoutExpired):
            pass
    return "device name not known" if backend == "cuda" else "a Vulkan device"
