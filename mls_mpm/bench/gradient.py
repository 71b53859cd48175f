"""`mls-mpm bench gradient`: forward, manual backward and ti.ad.Tape speed and peak memory.

Each measurement runs in its own process (peak memory is per process), and every ratio is taken between
figures measured in the same invocation. Compile time is excluded by a warm-up pass, and the compiler's
memory by running each child twice (the first fills Taichi's offline cache).
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

    arch = case.get("arch", "cpu")
    cfg = SimConfig(n_grid=case["n_grid"], steps=steps, dt=1e-4, E=1e3, nu=0.2, density=1.0, gamma=0.5,
                    stride=min(10, steps), dtype=case["dtype"], threads=THREADS if arch == "cpu" else 0,
                    schedule=case.get("schedule", "auto"), arch=arch)
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
    from .runtime import running_arch

    out["peak_mib"] = _peak_mib()
    out["backend"] = running_arch()
    print(json.dumps(out))


def _child(case_name, path, steps, tiny=False):
    case = dict(CASES[case_name]) if isinstance(case_name, str) else dict(case_name)
    if tiny:  # the same kernels at a negligible size: what the process holds besides the fields
        case.update(particles=64)
        steps = 2
    cmd = [sys.executable, "-c", f"from mls_mpm.bench import measure; measure({case!r}, {path!r}, {steps})"]
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "TI_LOG_LEVEL": "error"})
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("{")]
    if res.returncode or not lines:
        raise RuntimeError(f"benchmark child failed ({case_name}, {path}):\n{res.stderr[-2000:]}")
    return json.loads(lines[-1])


def backend_here(arch):
    """The backend `arch` starts on this machine (runtime.ensure, in a child process, so that the caller's
    Taichi stays as it is), or ArchError with runtime's one-line reason."""
    from .runtime import ArchError

    cmd = [sys.executable, "-c", "from mls_mpm import SimConfig, runtime; "
           f"runtime.ensure(SimConfig(arch={arch!r})); print(runtime.running_arch())"]
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "TI_LOG_LEVEL": "error"})
    if res.returncode:
        raise ArchError((res.stderr.strip().splitlines() or ["?"])[-1].split(": ", 1)[-1])
    return res.stdout.split()[-1]


def bench_gradient(quick=False, emit=print, arch="cpu", out=None):
    """Print the gradient benchmark as a markdown table (and return its rows); out: also write it there."""
    backend = backend_here(arch)
    lines = []

    def say(text):
        lines.append(text)
        emit(text)

    def warm(*args, **kwargs):
        """A child run twice, the second measured: the first fills Taichi's offline cache, so that neither
        peak RSS holds the compiler's memory (the sizes are compile-time constants: the tiny runs compile
        kernels of their own)."""
        _child(*args, **kwargs)
        return _child(*args, **kwargs)

    rows = []
    for name, case in CASES.items():
        case = dict(case, arch=arch)
        steps = 40 if quick else case["steps"]
        man = warm(case, "manual", steps)
        tape = warm(case, "tape", steps)
        if backend == "cpu":  # on a GPU the fields live in device memory: host RSS says nothing of them
            man["peak_mib"] -= warm(case, "manual", steps, tiny=True)["peak_mib"]
            tape["peak_mib"] -= warm(case, "tape", steps, tiny=True)["peak_mib"]
        rows.append((name, case, steps, man, tape))
    where = f"Taichi CPU, {THREADS} threads" if backend == "cpu" else f"Taichi {backend} ({_device_name(backend)})"
    memory = ("peak RSS of the path's process minus that of the same path at 64 particles and 2 steps (Python, "
              "Taichi and the compiled kernels), i.e. the memory the data needs" if backend == "cpu" else
              "not measured (the fields live in device memory; the estimate of the preallocated fields is in "
              "the scaling table)")
    say(f"{where}. Memory: {memory}.\n")
    say("| case | fwd ms/step | particle-steps/s | manual bwd ms/step | bwd / fwd | Tape fwd+bwd ms/step | "
        "Tape / manual (fwd+bwd) | manual MiB | Tape MiB | manual / Tape memory |")
    say("|---|---|---|---|---|---|---|---|---|---|")
    for name, case, steps, man, tape in rows:
        if {man["backend"], tape["backend"]} != {backend}:
            raise RuntimeError(f"benchmark children ran on {man['backend']} / {tape['backend']}, not {backend}")
        fwd, bwd, tp = man["forward_ms"], man["backward_ms"], tape["tape_ms"]
        m_man, m_tape = man["peak_mib"], tape["peak_mib"]
        mem = f"{m_man:.0f} | {m_tape:.0f} | {m_man / m_tape:.2f}" if backend == "cpu" else "- | - | -"
        label = f"{case['dtype']}, {case['n_grid']}^2 grid, {case['particles']} particles, {steps} steps"
        say(f"| {label} | {fwd:.3f} | {case['particles'] / fwd * 1e3 / 1e6:.2f} M | {bwd:.3f} | {bwd / fwd:.2f} | "
            f"{tp:.3f} | {tp / (fwd + bwd):.2f} | {mem} |")
    if out:
        from .checkpoint import atomic_write

        atomic_write(out, lambda fh: fh.write(("\n".join(lines) + "\n").encode()))
    return rows


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


# Scaling sweeps (issue 5): one quantity varied from the large case at a time.
SWEEPS = {
    "particles": [1024, 4096, 16384, 65536],
    "steps": [50, 200, 800],
    "n_grid": [32, 64, 128, 256],
}


def bench_scaling(quick=False, emit=print, plot_path="scaling.png"):
    """Forward, manual backward and Tape ms/step and peak memory against particles, steps and grid."""
    from .config import SimConfig
    from .memory import estimate_bytes

    base = dict(CASES["large"], steps=100 if quick else 200)
    results = {}
    emit("| varied | value | fwd ms/step | manual bwd ms/step | Tape fwd+bwd ms/step | manual peak MiB | "
         "Tape peak MiB | field estimate MiB |")
    emit("|---|---|---|---|---|---|---|---|")
    for key, values in SWEEPS.items():
        for v in values[:3] if quick else values:
            case = dict(base, **{key: v})
            steps = case["steps"]
            man = _child(case, "manual", steps)
            tape = _child(case, "tape", steps)
            cfg = SimConfig(n_grid=case["n_grid"], steps=steps, stride=10, dtype=case["dtype"])
            est = estimate_bytes(cfg, case["particles"]) / 2 ** 20
            results.setdefault(key, []).append((v, man["forward_ms"], man["backward_ms"], tape["tape_ms"]))
            emit(f"| {key} | {v} | {man['forward_ms']:.3f} | {man['backward_ms']:.3f} | {tape['tape_ms']:.3f} | "
                 f"{man['peak_mib']:.0f} | {tape['peak_mib']:.0f} | {est:.0f} |")
    per = 12 * 4  # x, v, C, F: 12 f32 words per particle-step (memory.estimate_bytes)
    emit(f"\nField memory grows linearly in particles x steps: {per} bytes per particle-step in f32 (twice that in "
         f"f64), plus 20 bytes per grid node per step (64^2: 80 KiB per step). 24 GiB holds about "
         f"{24 * 2 ** 30 / per / 1e6:.0f} million particle-steps in f32, e.g. 64k particles x "
         f"{24 * 2 ** 30 / per / 65536:.0f} steps; Simulator refuses larger scenes up front (sim.max_memory_gb).")
    _plot_scaling(results, plot_path)
    return results


def _plot_scaling(results, path):
    """Three log-log panels: ms/step of forward, manual backward and Tape against each varied quantity."""
    import math

    from PIL import Image, ImageDraw, ImageFont

    from .checkpoint import atomic_write

    W, H, pad = 300, 260, 46
    img = Image.new("RGB", (W * len(results), H), "white")
    d = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    colors = [(30, 30, 180), (200, 30, 30), (30, 140, 30)]
    for k, (key, pts) in enumerate(results.items()):
        ox = k * W
        xs = [math.log10(p[0]) for p in pts]
        ys = [math.log10(y) for p in pts for y in p[1:]]
        x0, x1 = min(xs) - 0.1, max(xs) + 0.1
        y0, y1 = math.floor(min(ys)), math.ceil(max(ys))
        y1 += y1 == y0

        def pt(x, y):
            return ox + pad + (W - pad - 10) * (x - x0) / (x1 - x0), 20 + (H - pad - 20) * (y1 - y) / (y1 - y0)

        d.rectangle([ox + pad, 20, ox + W - 10, H - pad], outline="black")
        d.text((ox + W / 2, H - 14), f"{key} (log)", fill="black", font=font, anchor="mm")
        for e in range(y0, y1 + 1):
            _, y = pt(x0, e)
            d.text((ox + pad - 4, y), f"1e{e}", fill="black", font=font, anchor="rm")
        for p in pts:
            x, _ = pt(math.log10(p[0]), y0)
            d.text((x, H - pad + 4), str(p[0]), fill="black", font=font, anchor="mt")
        for c, label in enumerate(("forward", "manual backward", "Tape fwd+bwd")):
            line = [pt(math.log10(p[0]), math.log10(p[1 + c])) for p in pts]
            d.line(line, fill=colors[c], width=2)
            if k == 0:
                d.text((ox + pad + 6, 24 + 12 * c), label, fill=colors[c], font=font)
        d.text((ox + pad, 6), "ms per step", fill="black", font=font)
    atomic_write(path, lambda fh: img.save(fh, format="PNG"))
