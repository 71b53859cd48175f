"""One measurement in a child process of its own (peak memory is per process): the benchmark cases, the
scene each runs, and the probes of the backend and the CPU model.

`run_child(case, path, steps)` starts `measure` in a fresh interpreter and reads back its JSON line: the
forward and manual backward ms/step ("manual") or ti.ad.Tape's forward+backward ms/step ("tape"), the
process's peak RSS and the backend it ran on (and the mls_mpm it imported: `tree` picks the source tree whose
code it runs). Compile time is excluded by a warm-up pass.
"""
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from ..config import COMPILE_VARIABLE, compile_mode

# The reference sizes: f32 at 64^2 with ~8k particles, and the thesis program's f64 32^2 / 1,245; in 3D (issue 12)
# f32 at 32^3 with ~16k particles and at 64^3 with ~100k, 30 steps each, and one window of the 3D successor's
# settings (32^3, 8 particles per cell volume in a ball of radius 8 cells, dt = 1/120, drag 0.5, a control
# every 10 of 30 steps, the thesis program's material E = 90000 dx^2, nu = 0.3, density 40).
CASES = {
    "large": dict(dtype="f32", n_grid=64, particles=8192, steps=200),
    "small": dict(dtype="f64", n_grid=32, particles=1245, steps=200),
    "3d": dict(dim=3, dtype="f32", n_grid=32, particles=16384, steps=30),
    "3d large": dict(dim=3, dtype="f32", n_grid=64, particles=100000, steps=30),
    "3d window": dict(dim=3, dtype="f32", n_grid=32, particles=17157, steps=30, window=True),
}
THREADS = 2
TINY_PARTICLES, TINY_STEPS = 64, 2  # run_child(tiny=True): the process without the fields' memory
WINDOW_CELLS = 8  # radius of the ball of the "3d window" case, in cells


def scene_of(case, steps):
    """A disk (3D: a ball) of `particles` particles centred in the domain, a mass loss toward a shifted one.

    The particles are drawn at random, so neighbours in memory are far apart in space; order="cell" numbers the
    same particles cell by cell (issue 14's "particles ordered by cell", measured on a GPU by gpu_cases.py)."""
    from ..config import SimConfig
    from ..losses import MassLoss

    arch = case.get("arch", "cpu")
    dim, n = case.get("dim", 2), case["n_grid"]
    common = dict(dim=dim, n_grid=n, steps=steps, stride=min(10, steps), dtype=case["dtype"],
                  threads=THREADS if arch == "cpu" else 0, schedule=case.get("schedule", "auto"), arch=arch)
    rng = np.random.default_rng(0)
    if dim == 2:
        cfg = SimConfig(dt=1e-4, E=1e3, nu=0.2, density=1.0, gamma=0.5, **common)
        r = 0.25 * np.sqrt(rng.uniform(0, 1, case["particles"]))
        a = rng.uniform(0, 2 * np.pi, case["particles"])
        x0 = 0.5 + np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
        from ..images import splat_grid

        target = splat_grid(x0 + [0.05, 0.02], cfg.m_p, n)
    else:
        if case.get("window"):
            radius = WINDOW_CELLS / n
            cfg = SimConfig(dt=1 / 120, E=90000.0 / n ** 2, nu=0.3, density=40.0, gamma=0.5, gravity=(0.0,) * 3,
                            particles_per_cell=8, **common)
        else:
            radius = 0.25
            cfg = SimConfig(dt=1e-4, E=1e3, nu=0.2, density=1.0, gamma=0.5, **common)
        u = rng.standard_normal((case["particles"], 3))
        x0 = 0.5 + radius * u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(0, 1, (len(u), 1)) ** (1 / 3)
        target = _ball_mass(n, 0.5 + np.array([0.05, 0.02, -0.03]), radius, len(x0) * cfg.m_p)
    if case.get("order") == "cell":  # the same particles, numbered cell by cell (row-major, as the grid lies)
        cells = np.clip(np.floor(x0 * n).astype(np.int64), 0, n - 1)
        x0 = x0[np.argsort(np.ravel_multi_index(tuple(cells.T), (n,) * dim), kind="stable")]
    controls = 0.01 * rng.standard_normal((cfg.n_controls, len(x0), dim, dim))
    return cfg, x0, MassLoss([target]), controls


def _ball_mass(n, center, radius, mass):
    """Node masses (n, n, n) of a ball of total mass `mass`, uniform inside with an edge one cell wide."""
    nodes = np.moveaxis(np.indices((n,) * 3) / n, 0, -1)
    inside = np.clip((radius - np.linalg.norm(nodes - center, axis=-1)) * n + 0.5, 0.0, 1.0)
    return mass * inside / inside.sum()


def _peak_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(case, path, steps):
    """Run in a child process: one path ("manual" or "tape"), print a JSON line of timings and peak memory."""
    cfg, x0, loss, controls = scene_of(case, steps)
    if path == "manual":
        from ..simulator import Simulator

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
        from ..tape import tape_gradient

        N, d = len(x0), cfg.dim
        init = {"x": x0, "v": np.zeros((N, d)), "C": np.zeros((N, d, d)), "F": np.tile(np.eye(d), (N, 1, 1))}
        _, _, state = tape_gradient(cfg, init, loss, controls)
        t0 = time.perf_counter()
        tape_gradient(cfg, init, loss, controls, state=state)
        t1 = time.perf_counter()
        out = {"tape_ms": (t1 - t0) / steps * 1e3}
    from ..runtime import running_arch

    out["peak_mib"] = _peak_mib()
    out["backend"] = running_arch()
    print(json.dumps(out))


def run_child(case_name, path, steps, tiny=False, tree=None):
    """`measure` of CASES[case_name] (or of a case dict) in a fresh interpreter; its result dict, with "mls_mpm":
    the file of the package the child imported.

    tiny=True: the same kernels at a negligible size, what the process holds besides the fields.
    tree: a source tree (the folder holding mls_mpm/ and adjoint/) whose code the child imports and whose own
    `measure` it calls, first on PYTHONPATH and its working folder (default: whatever this interpreter finds)."""
    case = dict(CASES[case_name]) if isinstance(case_name, str) else dict(case_name)
    if tiny:
        case.update(particles=TINY_PARTICLES)
        steps = TINY_STEPS
    code = ("import json, mls_mpm; print(json.dumps({'mls_mpm': mls_mpm.__file__}), flush=True); "
            f"from mls_mpm.bench.child import measure; measure({case!r}, {path!r}, {steps})")
    # the compile mode this process resolved, said explicitly: an older tree whose default differs compiles alike
    env = {**os.environ, "TI_LOG_LEVEL": "error", COMPILE_VARIABLE: compile_mode()}
    if tree is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(tree), env.get("PYTHONPATH")) if p)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=tree)
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode or len(lines) < 2:
        where = f" in {tree}" if tree is not None else ""
        raise RuntimeError(f"benchmark child failed ({case_name}, {path}{where}):\n{res.stderr[-2000:]}")
    return {k: v for ln in lines for k, v in json.loads(ln).items()}


def case_steps(case, quick):
    """The steps a case runs: its own, or with quick 40 (3D: 10) at the most."""
    return min(case["steps"], 40 if case.get("dim", 2) == 2 else 10) if quick else case["steps"]


def case_label(case, steps):
    """A case as a table's first column: dtype, grid, particles, steps."""
    dim = case.get("dim", 2)
    label = f"{case['dtype']}, {case['n_grid']}^{dim} grid, {case['particles']} particles, {steps} steps"
    if case.get("window"):
        label += " (one window of the 3D successor's settings)"
    if case.get("order") == "cell":
        label += ", sorted by cell"
    return label


def backend_here(arch):
    """The backend `arch` starts on this machine (runtime.ensure, in a child process, so that the caller's
    Taichi stays as it is), or ArchError with runtime's one-line reason."""
    from ..runtime import ArchError

    cmd = [sys.executable, "-c", "from mls_mpm import SimConfig, runtime; "
           f"runtime.ensure(SimConfig(arch={arch!r})); print(runtime.running_arch())"]
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "TI_LOG_LEVEL": "error"})
    if res.returncode:
        raise ArchError((res.stderr.strip().splitlines() or ["?"])[-1].split(": ", 1)[-1])
    return res.stdout.split()[-1]


def cpu_model():
    """The CPU's model name: "model name" in /proc/cpuinfo, else lscpu's "Model name", else what the platform says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    try:
        res = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=30)
        for line in res.stdout.splitlines():
            if line.startswith("Model name:"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.TimeoutExpired):
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
