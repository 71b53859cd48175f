"""The 3D fixed-corotated material (eq 9) and its closed-form reverse (eq 57, second term), in float64.

Forward: the polar rotation is a proper rotation with R^T F symmetric, also for inverted F. Reverse: against central
finite differences of stress (every case, repeated singular values included), against ti.ad.Tape through stress (cases
without repeated singular values: where F is inverted or ill-conditioned the Tape also differentiates the Jacobi
starting guess, whose derivative the Newton steps suppress only to ~1e-8; both of polar_rotation's methods, Higham's
iteration and the Jacobi SVD, are exercised, with F on either side of HIGHAM_Q), against linear elasticity at F = I,
and at the guarded singular set of tr(S) I - S. One kernel of each kind is compiled for all cases (the Tape one takes
about a minute).
"""
import numpy as np
import pytest
import taichi as ti

from conftest import rel_err
from mls_mpm.material import HIGHAM_Q, HIGHAM_TIERS, polar_rotation, stress
from test_adjoint_kernels import stress_adjoint, stress_functional  # dimension-generic (template fields)

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

MU, LAM = 123.4, 56.7
TAPE_TOL = 1e-8  # both exact in exact arithmetic; measured <= 1e-13
FD_TOL = 1e-6  # central differences, step 1e-6: truncation ~1e-12 |P'''|, cancellation ~1e-10; measured <= 1e-7
FD_STEP = 1e-6


def rot(axis, angle):
    """The rotation by `angle` about `axis` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


R0, R1 = rot([1, 2, 3], 0.7), rot([-2, 1, 0.5], 2.1)


def at_q(q):
    """The singular value a with J / (|F|_F^2 / 3)^(3/2) = q for F = R diag(a, 0.9, 1.2) R' (bisection: the ratio
    grows with a on [0, 0.9], up to 0.94)."""
    lo, hi = 0.0, 0.9
    for _ in range(200):
        a = 0.5 * (lo + hi)
        lo, hi = (a, hi) if a * 1.08 / ((a * a + 2.25) / 3.0) ** 1.5 < q else (lo, a)
    return 0.5 * (lo + hi)


rng = np.random.default_rng(11)
SMOOTH = {  # no repeated singular value
    "near I": np.eye(3) + 0.05 * rng.standard_normal((3, 3)),
    "large": 3.0 * rng.standard_normal((3, 3)),
    "rotated stretch": R0 @ np.diag([1.4, 0.8, 1.1]) @ R1,
    "shear": np.array([[1.0, 0.6, 0.2], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]]),
    "inverted": R1 @ np.diag([1.2, 0.9, -0.5]) @ R0,
    "nearly singular (J = 1e-9)": R0 @ np.diag([1.3, 0.7, 1e-9]) @ R1,
    "1e-3 from the singular set of M": R0 @ np.diag([1.5, 0.8, -0.799]) @ R1,
    # either side of the line between polar_rotation's two methods (Higham's iteration / the SVD and Newton steps)
    "just above HIGHAM_Q": R0 @ np.diag([at_q(1.02 * HIGHAM_Q), 0.9, 1.2]) @ R1,
    "just below HIGHAM_Q": R0 @ np.diag([at_q(0.98 * HIGHAM_Q), 0.9, 1.2]) @ R1,
    # and either side of each line between Higham step counts (HIGHAM_TIERS)
    **{f"just {side} q = {q}": R0 @ np.diag([at_q(k * q), 0.9, 1.2]) @ R1
       for q, _ in HIGHAM_TIERS for side, k in (("above", 1.02), ("below", 0.98))},
}
DIAGONAL_REPEATED = {  # repeated singular values but F^T F diagonal: Jacobi has nothing to rotate
    "identity": np.eye(3),
    "1.3 I": 1.3 * np.eye(3),
    "0.6 I": 0.6 * np.eye(3),
    "diag(1.2, 1.2, 0.7)": np.diag([1.2, 1.2, 0.7]),
}
ROTATED_REPEATED = {  # repeated singular values in a rotated frame: FD only (see the module docstring)
    "rotation": R0,
    "R0 1.1 I R1": R0 @ (1.1 * np.eye(3)) @ R1,
    "R1 diag(0.9, 1.3, 1.3) R0": R1 @ np.diag([0.9, 1.3, 1.3]) @ R0,
}
SINGULAR_M = np.diag([1.5, 0.8, -0.8])  # s2 + s3 = 0: tr(S) I - S singular, R not unique
CASES = {**SMOOTH, **DIAGONAL_REPEATED, **ROTATED_REPEATED, "singular M": SINGULAR_M}
NAMES = list(CASES)
FS = np.stack([CASES[k] for k in NAMES])
M = len(NAMES)


@ti.kernel
def rotation_kernel(Fs: ti.template(), out: ti.template()):
    for q in Fs:
        out[q] = polar_rotation(Fs[q])


@ti.kernel
def stress_kernel(Fs: ti.template(), out: ti.template(), mu: ti.f64, lam: ti.f64):
    for q in Fs:
        out[q] = stress(Fs[q], mu, lam)


def matrices(n):
    return ti.Matrix.field(3, 3, ti.f64, shape=n)


def run(kernel, X, *args):
    Fs, out = matrices(len(X)), matrices(len(X))
    Fs.from_numpy(np.asarray(X, float))
    kernel(Fs, out, *args)
    return out.to_numpy()


def reverse(X, G, mu=MU, lam=LAM):
    Fs, W, out = matrices(len(X)), matrices(len(X)), matrices(len(X))
    Fs.from_numpy(np.asarray(X, float))
    W.from_numpy(np.asarray(G, float))
    stress_adjoint(Fs, W, out, mu, lam)
    return out.to_numpy()


G = np.random.default_rng(12).standard_normal((M, 3, 3))


def test_polar_rotation_is_a_proper_rotation_with_symmetric_stretch():
    """R^T R = I, det R = 1 and S = R^T F symmetric to 1e-13 (relative to |F|), for inverted F too (then S has a
    negative eigenvalue); R = I at F = I, R = R0 at F = R0."""
    R = run(rotation_kernel, FS)
    for q, name in enumerate(NAMES):
        assert np.abs(R[q].T @ R[q] - np.eye(3)).max() <= 1e-13, name
        assert abs(np.linalg.det(R[q]) - 1.0) <= 1e-13, name
        S = R[q].T @ FS[q]
        assert np.abs(S - S.T).max() <= 1e-13 * np.abs(FS[q]).max(), name
        if np.linalg.det(FS[q]) < 0:
            assert np.linalg.eigvalsh(0.5 * (S + S.T)).min() < 0, name
    assert np.abs(R[NAMES.index("identity")] - np.eye(3)).max() == 0.0
    assert np.abs(R[NAMES.index("rotation")] - R0).max() <= 1e-14


def test_stress_vanishes_at_rest_and_extrudes_2d():
    """P(I) = 0, P(R0) = 0 to 1e-12. Extrusion F3 = blockdiag(F2, 1): its 2x2 block of P is the 2D P(F2) (cof F3
    holds cof F2 there and J is the same), P_22 = lam (J - 1) J (the z entry of cof F3 is J), the rest 0."""
    P = run(stress_kernel, np.stack([np.eye(3), R0]), MU, LAM)
    assert np.abs(P).max() <= 1e-12
    F2 = np.array([[1.2, 0.3], [-0.4, 0.9]])
    F3 = np.eye(3)
    F3[:2, :2] = F2
    P3 = run(stress_kernel, F3[None], MU, LAM)[0]
    c, s = F2[0, 0] + F2[1, 1], F2[1, 0] - F2[0, 1]  # the 2D polar angle, independently
    r = np.hypot(c, s)
    R2 = np.array([[c, -s], [s, c]]) / r
    J = np.linalg.det(F2)
    P2 = 2 * MU * (F2 - R2) + LAM * (J - 1) * J * np.linalg.inv(F2).T
    assert rel_err(P3[:2, :2], P2) <= 1e-13
    assert abs(P3[2, 2] - LAM * (J - 1) * J) <= 1e-12 * LAM
    assert np.abs(P3[:2, 2]).max() <= 1e-13 and np.abs(P3[2, :2]).max() <= 1e-13


def test_stress_reverse_matches_finite_differences():
    """stress_reverse(F, G) . D = d/dh [G : P(F + h D)] by central differences (step 1e-6), rel err <= 1e-6,
    for every case but the singular set of M, repeated singular values included (finite, no NaN)."""
    got = reverse(FS, G)
    assert np.all(np.isfinite(got))
    D = np.random.default_rng(13).standard_normal((M, 3, 3))
    plus = run(stress_kernel, FS + FD_STEP * D, MU, LAM)
    minus = run(stress_kernel, FS - FD_STEP * D, MU, LAM)
    fd = np.einsum("nij,nij->n", G, plus - minus) / (2 * FD_STEP)
    an = np.einsum("nij,nij->n", got, D)
    for q, name in enumerate(NAMES):
        if name != "singular M":
            assert rel_err(an[q], fd[q]) <= FD_TOL, name


def test_stress_reverse_matches_tape():
    """stress_reverse(F, G) = dP/dF : G vs ti.ad.Tape through stress: rel err <= 1e-8 (SMOOTH and diagonal
    repeated cases). At F = I also linear elasticity 2 mu sym(G) + lam tr(G) I to 1e-13, and not 2 mu G + ..."""
    names = list(SMOOTH) + list(DIAGONAL_REPEATED)
    X = np.stack([CASES[k] for k in names])
    Gs = np.stack([G[NAMES.index(k)] for k in names])
    Fs = ti.Matrix.field(3, 3, ti.f64, shape=len(names), needs_grad=True)
    W = matrices(len(names))
    loss = ti.field(ti.f64, shape=(), needs_grad=True)
    Fs.from_numpy(X)
    W.from_numpy(Gs)
    with ti.ad.Tape(loss=loss):
        stress_functional(Fs, W, loss, MU, LAM)
    tape, got = Fs.grad.to_numpy(), reverse(X, Gs)
    for q, name in enumerate(names):
        assert rel_err(got[q], tape[q]) <= TAPE_TOL, name
    q = names.index("identity")
    linear = MU * (Gs[q] + Gs[q].T) + LAM * np.trace(Gs[q]) * np.eye(3)
    assert rel_err(got[q], linear) <= 1e-13
    assert rel_err(got[q], 2 * MU * Gs[q] + LAM * np.trace(Gs[q]) * np.eye(3)) > 1e-3


def test_stress_reverse_at_the_singular_set_drops_the_rotation_term():
    """F = diag(1.5, 0.8, -0.8): s2 + s3 = 0, tr(S) I - S singular. Finite, and the rotation term's derivative is
    zero (the documented guard): the mu part is exactly 2 mu G. Near the set (1e-3 away) FD holds (above)."""
    q = NAMES.index("singular M")
    with_mu = reverse(SINGULAR_M[None], G[q][None], MU, LAM)[0]
    without = reverse(SINGULAR_M[None], G[q][None], 0.0, LAM)[0]
    assert np.all(np.isfinite(with_mu))
    assert rel_err(with_mu - without, 2 * MU * G[q]) <= 1e-13
