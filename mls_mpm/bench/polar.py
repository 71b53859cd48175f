"""Random deformation gradients and the 3D polar rotation of many of them at once, for benchmarks/polar_accuracy.py
and tests/test_polar_f32.py. Kernels compile for whatever Taichi the caller initialised (its float type)."""
import time

import numpy as np
import taichi as ti

from ..material import HIGHAM_Q, HIGHAM_STEPS, HIGHAM_TIERS, polar_rotation


def random_rotations(rng, n):
    """n uniform random rotations (n, 3, 3), from unit quaternions."""
    q = rng.standard_normal((n, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], 1)


def samples(n, seed=0, spread=2.5):
    """F = U diag(s) V^T (n, 3, 3) with log s uniform in [-spread, spread] times a uniform scale in [0, 1], a tenth of
    them inverted (the smallest singular value negated: then R = U V^T, the rotation-variant SVD's); returns F, its
    R = U V^T and q = J / (|F|_F^2 / 3)^(3/2), the measure that picks polar_rotation's method."""
    rng = np.random.default_rng(seed)
    U, V = random_rotations(rng, n), random_rotations(rng, n)
    s = np.exp(rng.uniform(-spread, spread, (n, 3)) * rng.uniform(0, 1, (n, 1)))
    inverted = np.arange(n) < n // 10
    s[inverted, np.argmin(s, axis=1)[inverted]] *= -1.0
    F = U @ (s[:, :, None] * np.eye(3)) @ V.transpose(0, 2, 1)
    return F, U @ V.transpose(0, 2, 1), q_measure(F)


def q_bands():
    """The bands of q that pick polar_rotation's method, highest first, as (low, high, float64 Higham steps):
    the Higham tiers (HIGHAM_TIERS), Higham's remaining band above HIGHAM_Q (HIGHAM_STEPS), and last the Jacobi
    SVD's band (steps None). A band holds low < q <= high."""
    out, hi = [], np.inf
    for lo, steps in (*HIGHAM_TIERS, (HIGHAM_Q, HIGHAM_STEPS)):
        out.append((lo, hi, steps))
        hi = lo
    return out + [(-np.inf, hi, None)]


def q_measure(F):
    """q = J / (|F|_F^2 / 3)^(3/2) of each F (n, 3, 3)."""
    return np.linalg.det(F) / ((F * F).sum((1, 2)) / 3.0) ** 1.5


@ti.data_oriented
class PolarKernel:
    """polar_rotation on n F at once, in the running Taichi's float type."""

    def __init__(self, n):
        self.n = n
        self.F = ti.Matrix.field(3, 3, float, shape=n)
        self.R = ti.Matrix.field(3, 3, float, shape=n)

    @ti.kernel
    def rotate(self):
        for p in range(self.n):
            self.R[p] = polar_rotation(self.F[p])

    def rotations(self, F):
        """R of each F (n, 3, 3), as float64."""
        self.F.from_numpy(F)
        self.rotate()
        return self.R.to_numpy().astype(np.float64)

    def ns_per_F(self, F, runs=5):
        """Nanoseconds per F of one launch on F (n, 3, 3), the minimum of `runs` (compile excluded)."""
        self.rotations(F)
        times = []
        for _ in range(runs):
            t = time.perf_counter()
            self.rotate()
            ti.sync()
            times.append(time.perf_counter() - t)
        return min(times) / self.n * 1e9
