"""Accuracy and speed of the 3D polar rotation of the stress (mls_mpm.material.polar_rotation), by starting guess.

    .venv/bin/python benchmarks/polar_accuracy.py [--count 400000] [--threads 2]

Random F = U diag(s) V^T (U, V uniform rotations, log s uniform in [-2.5, 2.5] times a uniform scale in [0, 1], a
tenth of them with the smallest negated: inverted), grouped by q = J / (|F|_F^2 / 3)^(3/2) into the bands of polar_rotation's
starting guesses (HIGHAM_TIERS: fewer Higham steps nearer a scaled rotation; HIGHAM_Q: Higham or the Jacobi SVD).
For each band: how many F, the largest |R - U V^T| (the sampled rotations; where F is nearly singular R is that
ill-conditioned) and the largest |R^T F - (R^T F)^T| / |F| in f64, and ns per F of a Taichi kernel computing R for
that band's F alone (f64 and f32, minimum of 5 runs, compile excluded).
Prints a Markdown table with the CPU model.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import taichi as ti  # noqa: E402

from mls_mpm.bench.child import cpu_model  # noqa: E402
from mls_mpm import material  # noqa: E402
from mls_mpm.material import HIGHAM_Q, HIGHAM_STEPS, polar_rotation  # noqa: E402

HIGHAM_TIERS = getattr(material, "HIGHAM_TIERS", ())  # none before 2026-12-03: HIGHAM_STEPS everywhere


def random_rotations(rng, n):
    q = rng.standard_normal((n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def samples(n, seed=0):
    rng = np.random.default_rng(seed)
    U, V = random_rotations(rng, n), random_rotations(rng, n)
    s = np.exp(rng.uniform(-2.5, 2.5, (n, 3)) * rng.uniform(0, 1, (n, 1)))
    inverted = np.arange(n) < n // 10
    s[inverted, np.argmin(s, axis=1)[inverted]] *= -1.0  # the smallest: then R = U V^T (rotation-variant SVD)
    F = U @ (s[:, :, None] * np.eye(3)) @ V.transpose(0, 2, 1)
    J = np.linalg.det(F)
    q = J / ((F * F).sum((1, 2)) / 3.0) ** 1.5
    return F, U @ V.transpose(0, 2, 1), q


def bands():
    """(label, low, high) of q, highest first: the Higham tiers, then Higham's remaining band, then the SVD's."""
    edges = [(f"q > {q} (Higham, {n} steps)", q) for q, n in HIGHAM_TIERS]
    edges.append((f"q > {HIGHAM_Q} (Higham, {HIGHAM_STEPS} steps)", HIGHAM_Q))
    out, hi = [], np.inf
    for label, lo in edges:
        out.append((label, lo, hi))
        hi = lo
    out.append((f"q <= {HIGHAM_Q}, inverted included (Jacobi SVD)", -np.inf, hi))
    return out


def run(dtype, F, threads, groups):
    """R for every F, and the ns per F of each group of F (indices) alone, tiled to len(F) (minimum of 5 runs)."""
    ti.init(arch=ti.cpu, default_fp=dtype, cpu_max_num_threads=threads, offline_cache=False, log_level="error")
    n = len(F)
    Ff = ti.Matrix.field(3, 3, dtype, shape=n)
    Rf = ti.Matrix.field(3, 3, dtype, shape=n)

    @ti.kernel
    def rotate():
        for p in range(n):
            Rf[p] = polar_rotation(Ff[p])

    Ff.from_numpy(F)
    rotate()
    R = Rf.to_numpy().astype(np.float64)
    ns = []
    for idx in groups:
        Ff.from_numpy(F[np.resize(idx, n)])
        times = []
        for _ in range(5):
            t = time.perf_counter()
            rotate()
            ti.sync()
            times.append(time.perf_counter() - t)
        ns.append(min(times) / n * 1e9)
    return R, ns


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=400_000)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    F, R_svd, q = samples(args.count)
    groups = [(label, np.flatnonzero((q > lo) & (q <= hi))) for label, lo, hi in bands()]
    groups = [(label, idx) for label, idx in groups if len(idx)]
    R, ns64 = run(ti.f64, F, args.threads, [idx for _, idx in groups])
    _, ns32 = run(ti.f32, F.astype(np.float32), args.threads, [idx for _, idx in groups])
    S = R.transpose(0, 2, 1) @ F
    err = np.abs(R - R_svd).max((1, 2))
    asym = np.abs(S - S.transpose(0, 2, 1)).max((1, 2)) / np.abs(F).max((1, 2))
    print(f"CPU: {cpu_model()}; {args.count} random F; {args.threads} threads; ns per F: that band's F alone\n")
    print("| q band | F | max abs(R - U V^T) | max asym(R^T F) / max abs(F) | ns per F, f64 | ns per F, f32 |")
    print("|---|---|---|---|---|---|")
    for (label, idx), t64, t32 in zip(groups, ns64, ns32):
        print(f"| {label} | {len(idx)} | {err[idx].max():.1e} | {asym[idx].max():.1e} | {t64:.0f} | {t32:.0f} |")


if __name__ == "__main__":
    main()
