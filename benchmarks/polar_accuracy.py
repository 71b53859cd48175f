"""Accuracy and speed of the 3D polar rotation of the stress (mls_mpm.material.polar_rotation), by method.

    .venv/bin/python benchmarks/polar_accuracy.py [--count 400000] [--threads 2]

Random F = U diag(s) V^T (U, V uniform rotations, log s uniform in [-2.5, 2.5] times a uniform scale in [0, 1], a
tenth of them with the smallest negated: inverted), grouped by q = J / (|F|_F^2 / 3)^(3/2) into the bands of
polar_rotation's methods (HIGHAM_TIERS: fewer Higham steps nearer a scaled rotation; HIGHAM_Q: Higham or the Jacobi
SVD).
For each band: how many F, the largest |R - U V^T| (the sampled rotations; where F is nearly singular R is that
ill-conditioned) and the largest |R^T F - (R^T F)^T| / |F| in f64, the largest |R - U V^T| in f32 (one Higham step
fewer: HIGHAM_F32_FEWER), and ns per F of a Taichi kernel computing R for that band's F alone (f64 and f32, minimum
of 5 runs, compile excluded).
Prints a Markdown table with the CPU model.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import taichi as ti  # noqa: E402

from mls_mpm.bench.child import cpu_model  # noqa: E402
from mls_mpm.bench.polar import PolarKernel, q_bands, samples  # noqa: E402
from mls_mpm.material import HIGHAM_F32_FEWER  # noqa: E402


def bands():
    """(label, low, high) of q, highest first (mls_mpm.bench.polar.q_bands)."""
    return [(f"q > {lo} (Higham, {n} steps; f32 {n - HIGHAM_F32_FEWER})" if n else
             f"q <= {hi}, inverted included (Jacobi SVD)", lo, hi) for lo, hi, n in q_bands()]


def run(dtype, F, threads, groups):
    """R for every F, and the ns per F of each group of F (indices) alone, tiled to len(F) (minimum of 5 runs)."""
    ti.init(arch=ti.cpu, default_fp=dtype, cpu_max_num_threads=threads, offline_cache=False, log_level="error")
    kernel = PolarKernel(len(F))
    R = kernel.rotations(F)
    return R, [kernel.ns_per_F(F[np.resize(idx, len(F))]) for idx in groups]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=400_000)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    F, R_svd, q = samples(args.count)
    groups = [(label, np.flatnonzero((q > lo) & (q <= hi))) for label, lo, hi in bands()]
    groups = [(label, idx) for label, idx in groups if len(idx)]
    R, ns64 = run(ti.f64, F, args.threads, [idx for _, idx in groups])
    R32, ns32 = run(ti.f32, F.astype(np.float32), args.threads, [idx for _, idx in groups])
    S = R.transpose(0, 2, 1) @ F
    err = np.abs(R - R_svd).max((1, 2))
    err32 = np.abs(R32 - R_svd).max((1, 2))
    asym = np.abs(S - S.transpose(0, 2, 1)).max((1, 2)) / np.abs(F).max((1, 2))
    print(f"CPU: {cpu_model()}; {args.count} random F; {args.threads} threads; ns per F: that band's F alone\n")
    print("| q band | F | max abs(R - U V^T) | max asym(R^T F) / max abs(F) | f32: max abs(R - U V^T) | ns per F, f64 "
          "| ns per F, f32 |")
    print("|---|---|---|---|---|---|---|")
    for (label, idx), t64, t32 in zip(groups, ns64, ns32):
        print(f"| {label} | {len(idx)} | {err[idx].max():.1e} | {asym[idx].max():.1e} | {err32[idx].max():.1e} | "
              f"{t64:.0f} | {t32:.0f} |")


if __name__ == "__main__":
    main()
