"""`mls-mpm bench gradient`: forward, manual backward and ti.ad.Tape speed and peak memory.

Each measurement runs in its own process (peak memory is per process), and every ratio is taken between
figures measured in the same invocation. Compile time is excluded by a warm-up pass.
"""
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

# The reference sizes: f32 at 64^2 with ~8k particles, and the thesis program's f64 32^2 / 1,245.
CASES = {
    "large": dict(dtype="f32", n_grid=64, particles=8192, steps=200),
    "small": dict(dtype="f64", n_grid=32, particles=1245, steps=200),
}
THREADS = 2


def _scene(case, steps):
    """A disk of `particles` particles centred in the domain, a mass loss toward a shifted disk."""
    from .config import SimConfig

    cfg = SimConfig(n_grid=case["n_grid"], steps=steps, dt=1e-4, E=1e3, nu=0.2, density=1.0, gamma=0.5,
                    stride=10, dtype=case["dtype"], threads=THREADS, schedule=case.get("schedule", "auto"))
    rng = np.random.default_rng(0)
    r = 0.25 * np.sqrt(rng.uniform(0, 1, case["particles"]))
    a = rng.uniform(0, 2 * np.pi, case["particles"])
    x0 = 0.5 + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    from .images import splat_grid
    from .losses import MassLoss

    target = splat_grid(x0 + [0.05, 0.02], cfg.m_p, cfg.n_grid)
    controls = 0.01 * rng.standard_normal((cfg.n_controls, len(x0), 2, 2))
    return cfg, x0, MassLoss([target]), controls


def _peak_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(case, path, steps):
    """Run in a child process: one path ("manual" or "tape"), print a JSON line of timings and peak memory."""
    cfg, x0, loss, controls = _scene(case, steps)
    if path == "manual":
        from .simulator import Simulator

        sim = Simulator(cfg, x0, loss=loss)
        sim.forward(controls)
        sim.backward()  # warm-up: compiles every kernel
        t0 = time.perf_counter()
        sim.forward(controls)
        t1 = time.perf_counter()
        sim.backward()
        t2 = time.perf_counter()
        out = {"forward_ms": (t1 - t0) / steps * 1e3, "backward_ms": (t2 - t1) / steps * 1e3}
    else:
        from .tape import tape_gradient

        N = len(x0)
        init = {"x": x0, "v": np.zeros((N, 2)), "C": np.zeros((N, 2, 2)), "F": np.tile(np.eye(2), (N, 1, 1))}
        _, _, state = tape_gradient(cfg, init, loss, controls)
        t0 = time.perf_counter()
        tape_gradient(cfg, init, loss, controls, state=state)
        t1 = time.perf_counter()
        out = {"tape_ms": (t1 - t0) / steps * 1e3}
    out["peak_mib"] = _peak_mib()
    print(json.dumps(out))


def _child(case_name, path, steps, tiny=False):
    case = dict(CASES[case_name])
    if tiny:  # the same kernels at a negligible size: what the process holds besides the fields
        case.update(particles=64)
        steps = 2
    cmd = [sys.executable, "-c", f"from mls_mpm.bench import measure; measure({case!r}, {path!r}, {steps})"]
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "TI_LOG_LEVEL": "error"})
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode or not lines:
        raise RuntimeError(f"benchmark child failed ({case_name}, {path}):\n{res.stderr[-2000:]}")
    return json.loads(lines[-1])


def bench_gradient(quick=False, emit=print):
    """Print the gradient benchmark as a markdown table (and return its rows)."""
    rows = []
    for name, case in CASES.items():
        steps = 40 if quick else case["steps"]
        man = _child(name, "manual", steps)
        tape = _child(name, "tape", steps)
        man["peak_mib"] -= _child(name, "manual", steps, tiny=True)["peak_mib"]
        tape["peak_mib"] -= _child(name, "tape", steps, tiny=True)["peak_mib"]
        rows.append((name, case, steps, man, tape))
    emit(f"Taichi CPU, {THREADS} threads. Memory: peak RSS of the path's process minus that of the same path at "
         "64 particles and 2 steps (Python, Taichi and the compiled kernels), i.e. the memory the data needs.\n")
    emit("| case | fwd ms/step | particle-steps/s | manual bwd ms/step | bwd / fwd | Tape fwd+bwd ms/step | "
         "Tape / manual (fwd+bwd) | manual MiB | Tape MiB | manual / Tape memory |")
    emit("|---|---|---|---|---|---|---|---|---|---|")
    for name, case, steps, man, tape in rows:
        fwd, bwd, tp = man["forward_ms"], man["backward_ms"], tape["tape_ms"]
        m_man, m_tape = man["peak_mib"], tape["peak_mib"]
        label = f"{case['dtype']}, {case['n_grid']}^2 grid, {case['particles']} particles, {steps} steps"
        emit(f"| {label} | {fwd:.3f} | {case['particles'] / fwd * 1e3 / 1e6:.2f} M | {bwd:.3f} | {bwd / fwd:.2f} | "
             f"{tp:.3f} | {tp / (fwd + bwd):.2f} | {m_man:.0f} | {m_tape:.0f} | {m_man / m_tape:.2f} |")
    return rows
