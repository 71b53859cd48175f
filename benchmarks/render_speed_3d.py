"""Milliseconds per 3D output frame (preview, particles PLY, mesh PLY) vs the simulation steps between two frames.

    python benchmarks/render_speed_3d.py [--n-grid 32] [--ppc 8] [--radius 0.25] [--size 512] [--every 5] [--repeats 5]

A ball of particles at the author's settings (32^3 grid, 8 particles per cell, on a lattice), as render_run
writes each frame of a 3D run: the field (field3d.mass_field: P2G of mass and colour), the preview in each mode
(Preview3D.render, then FrameWriter.write: PNG and the atomic write), particles/frame.ply (G2P density and the
write) and meshes/frame.ply (marching cubes, vertex colours and the write). Then `Simulator.forward` over `every`
steps from the ball at rest, if a 3D Simulator compiles on this revision. Compile time is excluded; each figure
is the median of `repeats` calls, wall time and in brackets the process CPU time (all threads).
"""
import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import mls_mpm  # noqa: E402
from mls_mpm import runtime  # noqa: E402
from mls_mpm.export3d import MODES_3D, PLY_NAME, PLY_RE, surface, write_mesh, write_particles  # noqa: E402
from mls_mpm.field3d import frame_field  # noqa: E402
from mls_mpm.frames import FrameWriter  # noqa: E402
from mls_mpm.render3d import Preview3D  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from render_speed import best_ms as median_ms  # noqa: E402  the 2D script's timer: median wall and CPU ms


def ball(n_grid, ppc, radius):
    k = round(ppc ** (1 / 3))
    s = (np.arange(n_grid * k) + 0.5) / (n_grid * k)
    x = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    return x[np.linalg.norm(x - 0.5, axis=1) < radius]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--n-grid", type=int, default=32)
    parser.add_argument("--ppc", type=int, default=8, help="particles per cell")
    parser.add_argument("--radius", type=float, default=0.25, help="the ball's radius (domain units)")
    parser.add_argument("--size", type=int, default=512, help="image side in pixels")
    parser.add_argument("--every", type=int, default=5, help="simulation steps between two frames")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dtype", default="f64", choices=mls_mpm.config.DTYPES)
    args = parser.parse_args(argv)

    cfg = mls_mpm.SimConfig(dim=3, n_grid=args.n_grid, steps=args.every, stride=args.every, dt=1 / 120, E=90.0,
                            nu=0.3, density=40.0, gamma=0.5, gravity=(0.0, 0.0, 0.0),
                            particles_per_cell=args.ppc, dtype=args.dtype)
    runtime.ensure(cfg)
    x = ball(args.n_grid, args.ppc, args.radius)
    colors = np.clip(x * 1.5 - 0.25, 0, 1)
    print(f"{len(x)} particles, {args.n_grid}^3 grid, {args.size}^2 pixels, cpu, {args.dtype}")
    rows = []
    field, density = frame_field(x, cfg.m_p, cfg.n_grid, cfg.density, colors)
    rows.append(("field (P2G of m and c, G2P density)",
                 median_ms(lambda: frame_field(x, cfg.m_p, cfg.n_grid, cfg.density, colors), args.repeats)))
    with tempfile.TemporaryDirectory() as tmp:
        for mode in MODES_3D:
            preview = Preview3D(cfg.n_grid, args.size, mode, spacing=cfg.dx / args.ppc ** (1 / 3))
            rows.append((f"preview {mode}", median_ms(lambda: preview.render(field, x, colors), args.repeats)))
            writer = FrameWriter(tmp, folder=mode)
            frame = preview.render(field, x, colors)
            rows.append((f"  + FrameWriter.write {mode}", median_ms(lambda: writer.write(frame), args.repeats)))
        particles = FrameWriter(tmp, folder="particles", name=PLY_NAME, pattern=PLY_RE, save=write_particles)
        rows.append(("particles .ply", median_ms(lambda: particles.write((x, colors, density)), args.repeats)))
        meshes = FrameWriter(tmp, folder="meshes", name=PLY_NAME, pattern=PLY_RE, save=write_mesh)
        rows.append(("mesh .ply (marching cubes, colours, write)",
                     median_ms(lambda: meshes.write(surface(field)), args.repeats)))
    for name, (wall, cpu) in rows:
        print(f"{name:<44} {wall:8.2f} ms/frame  (cpu {cpu:.2f} ms)")
    try:
        sim = mls_mpm.Simulator(cfg, x)
        controls = np.zeros((cfg.n_controls, len(x), 3, 3))
        wall, cpu = median_ms(lambda: sim.forward(controls), args.repeats)
        print(f"simulate {args.every} steps (one frame)          {wall:8.2f} ms  (cpu {cpu:.2f} ms; "
              f"{wall / args.every:.2f} ms/step)")
    except Exception as e:  # a revision whose 3D material is not there yet
        print(f"simulate {args.every} steps: unavailable on this revision ({type(e).__name__}: "
              f"{str(e).splitlines()[0] if str(e) else ''})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
