"""Milliseconds per rendered frame vs milliseconds of the simulation steps between two frames.

    python benchmarks/render_speed.py [--arch cpu] [--size 512] [--n-grid 64] [--every 5] [--repeats 20]

Renders ~8k particles (a 45 x 45 cell block at 4 particles per cell on a 64^2 grid) in each mode, times
`FrameWriter.write` of the rendered mass and color frames (PNG encoding and the atomic file write), and times
`Simulator.forward` over `every` steps (the steps between two saved frames). Compile time is excluded; each
figure is the median of `repeats` calls: wall time, and in brackets the process CPU time (all threads), which
other work on a shared machine disturbs less (on an idle machine, wall ~ CPU / threads for parallel kernels).
"""
import argparse
import tempfile
import time

import numpy as np
import taichi as ti

import mls_mpm
from mls_mpm import runtime
from mls_mpm.frames import FRAME_NAME, FrameWriter
from mls_mpm.problem import rest_node_mass
from mls_mpm.render import Renderer


def block_particles(cfg, cells=45, lo=0.15):
    """cells x cells cells from lo, at 2 x 2 particles per cell: cells^2 * 4 particles."""
    k = int(round(cfg.particles_per_cell ** 0.5))
    s = lo + (np.arange(cells * k) + 0.5) * cfg.dx / k
    return np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)


def best_ms(fn, repeats):
    """Median wall time and median process CPU time of fn() in ms, after one warm-up call (compilation)."""
    fn()
    ti.sync()
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ti.sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--arch", default="cpu", choices=mls_mpm.config.ARCHS)
    parser.add_argument("--dtype", default="f64", choices=mls_mpm.config.DTYPES)
    parser.add_argument("--size", type=int, default=512, help="image side in pixels")
    parser.add_argument("--n-grid", type=int, default=64)
    parser.add_argument("--every", type=int, default=5, help="simulation steps between two frames")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args(argv)

    cfg = mls_mpm.SimConfig(n_grid=args.n_grid, steps=args.every, stride=args.every, arch=args.arch,
                            dtype=args.dtype)
    runtime.ensure(cfg)
    x = block_particles(cfg)
    rng = np.random.default_rng(0)
    F = np.eye(2) + 0.2 * rng.standard_normal((len(x), 2, 2))
    colors = np.where(x[:, :1] < 0.5, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    rest = rest_node_mass(cfg, cfg.n_grid)
    target = np.zeros((cfg.n_grid, cfg.n_grid))
    target[16:48, 16:48] = rest
    print(f"{len(x)} particles, {cfg.n_grid}^2 grid, {args.size}^2 pixels, arch {args.arch}, {args.dtype}")

    frames = {}
    for mode, extra in (("mass", {}), ("color", {"colors": colors}), ("particles", {}),
                        ("particles", {"F": F}), ("mass", {"target_outline": target})):
        r = Renderer(cfg.n_grid, len(x), args.size, rest, mode,
                     body_outline="target_outline" in extra)
        ms, cpu = best_ms(lambda: r.render(x, cfg.m_p, **extra), args.repeats)
        what = mode + "".join(f" +{k}" for k in extra if k != "colors")
        print(f"render {what:<28s} {ms:8.2f} ms/frame  (cpu {cpu:.2f} ms)")
        frames.setdefault(mode, r.render(x, cfg.m_p, **extra))

    with tempfile.TemporaryDirectory() as out:
        writer = FrameWriter(out)
        for mode in ("mass", "color"):
            ms, cpu = best_ms(lambda: writer.write(frames[mode]), args.repeats)
            size = (writer.frames_dir / FRAME_NAME.format(writer.count - 1)).stat().st_size
            print(f"FrameWriter.write {mode + ' frame':<17s} {ms:8.2f} ms/frame  (cpu {cpu:.2f} ms, "
                  f"{size / 1024:.0f} KiB PNG)")

    sim = mls_mpm.Simulator(cfg, x)
    controls = sim.zero_controls()
    ms, cpu = best_ms(lambda: sim.forward(controls), args.repeats)
    print(f"simulate {args.every} steps (one frame)  {ms:8.2f} ms  (cpu {cpu:.2f} ms; {ms / args.every:.2f} ms/step)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
