"""Sinkhorn iterations and time of the OT loss on the morph suite's grids (mls_mpm/ot.py).

    .venv/bin/python benchmarks/sinkhorn_speed.py

For four pairs of scenes/images/pairs (sampled as `mls-mpm morph --quality default` samples them: 64^2 grid, 4
particles per cell, the target moved onto the body's centre of mass), the debiased divergence between the body's
and the target's node masses on the 32^2 and 64^2 loss grids at morph's blur (2 cells), balanced: iterations and
milliseconds at the production tolerance (losses.OT_TOL) with the over-relaxed updates (ot.RELAX) and with plain
alternating updates (relax = 1), and the gradient's largest difference from a run to tol 1e-12, relative to its
largest entry. Prints a Markdown table with the CPU model.
"""
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mls_mpm import morph, ot  # noqa: E402
from mls_mpm.bench.quality import PAIRS_DIR, cpu_model  # noqa: E402
from mls_mpm.images import load_image, sample_particles, splat_grid  # noqa: E402
from mls_mpm.losses import OT_BLUR, OT_TOL  # noqa: E402

PAIRS = ("letter_L_thin", "split_three", "shrink_disk", "letter_C")
N_GRID = 64


def grids(name):
    x0, _ = sample_particles(load_image(PAIRS_DIR / f"{name}_initial.png"), N_GRID, 4)
    xt, _ = sample_particles(load_image(PAIRS_DIR / f"{name}_target.png"), N_GRID, 4)
    xt = xt + morph.centring_shift(x0, xt, N_GRID)
    for res in (N_GRID // 2, N_GRID):
        yield res, splat_grid(x0, 1.0, res), splat_grid(xt, len(x0) / len(xt), res)


def timed(a, b, blur, **kw):
    t = time.perf_counter()
    r = ot.sinkhorn_divergence(a, b, blur, **kw)
    return r, 1e3 * (time.perf_counter() - t)


def main():
    print(f"CPU: {cpu_model()}; tol {OT_TOL:g} (losses.OT_TOL), blur {OT_BLUR:g} cells, relax {ot.RELAX}")
    print()
    print("| pair | grid | iterations (relax) | ms | gradient error | iterations (plain) | ms (plain) |")
    print("|---|---|---|---|---|---|---|")
    for name in PAIRS:
        for res, a, b in grids(name):
            blur = OT_BLUR / res
            ref = ot.sinkhorn_divergence(a, b, blur, tol=1e-12)
            fast, ms = timed(a, b, blur, tol=OT_TOL)
            plain, ms_plain = timed(a, b, blur, tol=OT_TOL, relax=1.0)
            err = np.abs(fast.grad - ref.grad).max() / np.abs(ref.grad).max()
            print(f"| {name} | {res}^2 | {fast.iterations} | {ms:.0f} | {err:.1e} | {plain.iterations} | "
                  f"{ms_plain:.0f} |", flush=True)


if __name__ == "__main__":
    main()
