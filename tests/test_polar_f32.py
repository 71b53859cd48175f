"""The 3D polar rotation (eq 9's R) in float32, where polar_rotation takes one Higham step fewer in every band
(material.HIGHAM_F32_FEWER): the rotation must stay at float32 round-off against U V^T of the sampled SVD.

Random F = U diag(s) V^T with the singular values drawn so that every band of q = J / (|F|_F^2 / 3)^(3/2) gets F
(mls_mpm.bench.polar's q_bands: the Higham tiers and the Jacobi SVD's q <= HIGHAM_Q; its samples, as
benchmarks/polar_accuracy.py's). One kernel, compiled once in float32.
"""
import numpy as np
import pytest

import mls_mpm
from mls_mpm import runtime
from mls_mpm.bench.polar import PolarKernel, q_bands, q_measure, samples

COUNT = 20_000
# float32 round-off of R (~6e-8 an entry) times the few operations of the last Higham step; measured: <= 3.1e-7 in
# the Higham bands (benchmarks/polar_accuracy.py). One Higham step fewer still would leave ~7e-4.
F32_TOL = 5e-6
# the Jacobi SVD band: F there is nearly singular or inverted, and R's sensitivity grows as 1 / (s_i + s_j)
SVD_TOL = 1e-3


@pytest.fixture(scope="module")
def rotations():
    """(q, R of polar_rotation in float32, U V^T in float64) for COUNT random F; Taichi back to float64 after."""
    F, _, _ = samples(COUNT, seed=32, spread=2.0)
    F32 = F.astype(np.float32)
    F64 = F32.astype(np.float64)  # the F the kernel sees
    runtime.ensure(mls_mpm.SimConfig(dtype="f32", arch="cpu"), tape=False)
    try:
        R = PolarKernel(COUNT).rotations(F32)
    finally:
        runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"), tape=False)
    # the reference: the polar rotation of the rounded F, from numpy's SVD in float64 (det U, det V fixed to +1, the
    # smallest singular value carrying the sign of J, as polar_rotation's rotation-variant SVD)
    u, _, vt = np.linalg.svd(F64)
    d = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    u[:, :, 2] *= d[:, None]
    return q_measure(F64), R, u @ vt


@pytest.mark.parametrize("band", range(len(q_bands()) - 1))
def test_higham_bands_reach_f32_round_off(rotations, band):
    """Each Higham band (one step fewer in float32): |R - U V^T| <= F32_TOL, R a rotation to round-off."""
    q, R, ref = rotations
    lo, hi, _ = q_bands()[band]
    idx = (q > lo) & (q <= hi)
    assert idx.sum() > 500, f"band q in ({lo}, {hi}]: too few samples"
    err = np.abs(R[idx] - ref[idx]).max()
    assert err <= F32_TOL, f"band q in ({lo}, {hi}]: max |R - U V^T| = {err:.2e}"
    ortho = np.abs(R[idx].transpose(0, 2, 1) @ R[idx] - np.eye(3)).max()
    assert ortho <= F32_TOL, f"band q in ({lo}, {hi}]: max |R^T R - I| = {ortho:.2e}"


def test_svd_band_is_a_rotation(rotations):
    """The Jacobi SVD band (q <= HIGHAM_Q, inverted F included; unchanged by the float type): R is a proper rotation
    and near U V^T as far as F's conditioning allows."""
    q, R, ref = rotations
    lo, hi, _ = q_bands()[-1]
    idx = (q > lo) & (q <= hi)
    assert idx.sum() > 500
    assert np.abs(R[idx].transpose(0, 2, 1) @ R[idx] - np.eye(3)).max() <= F32_TOL
    assert np.all(np.linalg.det(R[idx]) > 0.99)
    assert np.median(np.abs(R[idx] - ref[idx]).max((1, 2))) <= SVD_TOL
