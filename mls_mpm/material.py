"""Fixed-corotated elasticity (eq 9): P(F) = 2 mu (F - R) + lambda (J - 1) J F^{-T}, in 2D and 3D.

Only the polar rotation R and the cofactor J F^{-T} differ by dimension (chosen by ti.static(F.n == 2)):
in 2D R is the closed-form polar angle; in 3D R = U V^T of a rotation-variant SVD F = U Sigma V^T (U, V
proper rotations, the smallest singular value carrying the sign of J, so R is a rotation also for inverted F). For a
well-conditioned F with J > 0 (the common case) Higham's scaled Newton iteration for the polar factor, run to
round-off; else a Jacobi eigen-solver on F^T F, polished to round-off by Newton steps on SO(3). Every loop has a
fixed trip count, so ti.ad.Tape differentiates it (Taichi's ti.svd cannot be: its sifakis kernel uses bit casts).
"""
import taichi as ti
from taichi.lang import impl

from .kernels import spirv


# 3x3 products written as expressions: Taichi's `@` accumulates into local variables, which ti.ad.Tape turns
# into stacks and compiles some 30 times slower (34 s against 1.2 s for one Newton step).
@ti.func
def _mul(A, B):
    return ti.Matrix([[A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j] for j in ti.static(range(3))]
                      for i in ti.static(range(3))])


@ti.func
def _mulv(A, b):
    return ti.Vector([A[i, 0] * b[0] + A[i, 1] * b[1] + A[i, 2] * b[2] for i in ti.static(range(3))])


@ti.func
def cross_matrix(w):
    """[w]_x, the skew matrix with [w]_x a = w x a."""
    return ti.Matrix([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


@ti.func
def axial(K):
    """The vector w of a skew matrix K = [w]_x, read as (K21, K02, K10) (K need not be skew: its skew part's)."""
    return ti.Vector([K[2, 1], K[0, 2], K[1, 0]])


@ti.func
def cofactor(F):
    """J F^{-T} written without a division, so J -> 0 is harmless.

    2D: [[F11, -F10], [-F01, F00]]. 3D: the columns f1 x f2, f2 x f0, f0 x f1 of the columns f0, f1, f2 of F.
    """
    if ti.static(F.n == 2):
        return ti.Matrix([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])
    else:
        f0, f1, f2 = F[:, 0], F[:, 1], F[:, 2]
        return ti.Matrix.cols([f1.cross(f2), f2.cross(f0), f0.cross(f1)])


# Below this squared norm of (F00 + F11, F10 - F01) the polar angle is undefined (F symmetric with zero trace).
ROTATION_EPS = 1e-20

# 3D: below this det(M) / tr(M)^3, M = tr(S) I - S is taken as singular (two singular values of F sum to zero,
# det M = (s1 + s2)(s1 + s3)(s2 + s3)): R is not unique there. About a smallest eigenvalue of M below 1e-9 tr(M),
# far above float64 round-off (1e-16) and far below any F a simulation reaches except through exact degeneracy.
POLAR_EPS = 1e-10

JACOBI_SWEEPS = 3  # cyclic sweeps of the 3x3 Jacobi eigen-solver: a start good to ~1e-8 or better
NEWTON_STEPS = 2  # quadratic: a start within 1e-4 ends at round-off
# Higham's iteration (higham_rotation) is taken where J > HIGHAM_Q (|F|_F^2 / 3)^(3/2), i.e. J over the volume of the
# cube with F's mean squared singular value: 1 for a scaled rotation, 0 for a singular F. Above it HIGHAM_STEPS
# iterations reach float64 round-off (measured: <= 1e-14 on 500k random F with q > 1e-3; the error shrinks
# quadratically once it is below ~0.1, the scaling gets it there in a few steps), and so does their derivative: the
# iteration's dX/dF, which ti.ad.Tape takes, is the polar rotation's dR/dF to 6e-14 relative at the step counts below
# (numpy, forward-mode, 20k random F with q > 0.01). No Newton step follows (one cost 38 ns of the 108 ns a float32
# R took, for the same accuracy: BENCHMARKS.md, "The 3D polar rotation without its Newton step").
HIGHAM_Q = 0.01
HIGHAM_STEPS = 6
# Fewer steps where F is nearer a scaled rotation (the common case, moderate strain), by the same q: (q above,
# steps), tried in order. The last step of each count is unscaled (z = 1: the iterate's det is 1 to ~1e-8 by then).
# Measured on 400k random F (numpy, f64), the largest |X - R| of the iteration: q > 0.85 after 4 steps, q > 0.2 after 5,
# q > 0.01 after 6, each 1.4e-15 (and 5.2e-15 at q > 0.8 after 4 steps, 1.4e-15 at q > 0.01 after 6 scaled steps);
# benchmarks/polar_accuracy.py measures the Taichi code's.
HIGHAM_TIERS = ((0.9, 4), (0.3, 5))
HIGHAM_MIN_STEPS = min(n for _, n in HIGHAM_TIERS)
# In float32 R needs float32 round-off only (~1e-7): one Higham step fewer in every band. Measured (the Taichi code
# in float32, benchmarks/polar_accuracy.py, 200k random F): the largest |R - U V^T| after HIGHAM_TIERS' counts minus
# one is 1.6e-7, 1.7e-7 and 3.1e-7 by band, as with the float64 counts; two fewer leave 7e-4 (numpy; a Newton step on
# SO(3) after them would not help: it corrects a rotation, not X's symmetric part). tests/test_polar_f32.py checks it.
HIGHAM_F32_FEWER = 1


def higham_fewer():
    """The Higham steps fewer than HIGHAM_TIERS and HIGHAM_STEPS say, for the running Taichi's float type (fixed at
    compile time: call it inside ti.static)."""
    return HIGHAM_F32_FEWER if impl.current_cfg().default_fp == ti.f32 else 0


@ti.func
def rotation_solve(S, h):
    """omega with (tr(S) I - S) omega = h for symmetric S (the rotation's linearisation, eq 9's R), by the adjugate.

    Where M = tr(S) I - S is singular (det M <= POLAR_EPS tr(M)^3) omega = 0 is returned, as the 2D guard does.
    """
    M = S.trace() * ti.Matrix.identity(float, 3) - S
    cM = cofactor(M)
    d = M[:, 0].dot(cM[:, 0])
    t = M.trace()
    regular = d > POLAR_EPS * t * t * t  # guard: two singular values sum to zero, R is not unique (see POLAR_EPS)
    # M symmetric: M^{-1} = cof(M)^T / det M = cof(M) / det M
    return ti.select(regular, 1.0, 0.0) * _mulv(cM, h) / ti.select(regular, d, 1.0)


@ti.func
def cayley(w):
    """The rotation (I - [w/2]_x)^{-1} (I + [w/2]_x) = I + 2 ([a] + [a]^2) / (1 + a.a), a = w / 2: I + [w]_x to
    first order, exactly orthogonal and smooth at w = 0 (no angle, no square root)."""
    A = cross_matrix(0.5 * w)
    return ti.Matrix.identity(float, 3) + 2.0 / (1.0 + 0.25 * w.dot(w)) * (A + _mul(A, A))


# The starting guess below is branch-free (ti.select), so that ti.ad.Tape differentiates it quickly; its
# derivative does not matter (the Newton steps of polar_rotation remove it), only that it stays finite.
# A pair whose |d| and |C_pq| are below JACOBI_EPS tr(C) is rotated only partly (those eigenvectors are nearly
# degenerate and do not change R): keeps the Jacobi derivative bounded, which the Newton steps then remove.
JACOBI_EPS = 1e-8


@ti.func
def jacobi_rotate(C, V, p: ti.template(), q: ti.template()):
    """One Jacobi rotation G in the (p, q) plane zeroing C_pq: returns (G^T C G, V G) (Golub and Van Loan 8.5.2).

    t = tan(theta) = 2 C_pq / (|d| + sqrt(d^2 + 4 C_pq^2)) sign(d), d = C_qq - C_pp, sign(0) = +1, |theta| <= pi / 4
    (t = 0 where C_pq = 0), c = cos(theta), s = sin(theta), G_pp = G_qq = c, G_pq = s, G_qp = -s.
    """
    o = C[p, q]
    d = C[q, q] - C[p, p]
    tiny = (JACOBI_EPS * C.trace()) ** 2  # guard: 0 / 0 at o = d = 0, and bounded derivatives near it
    t = 2.0 * o / (ti.abs(d) + ti.sqrt(d * d + 4.0 * o * o + tiny))
    t = ti.select(d < 0.0, -t, t)
    c = 1.0 / ti.sqrt(1.0 + t * t)
    s = t * c
    G = ti.Matrix([[c if i == j and (i == p or i == q) else s if (i, j) == (p, q) else -s if (i, j) == (q, p)
                    else 1.0 if i == j else 0.0 for j in ti.static(range(3))] for i in ti.static(range(3))])
    return _mul(_mul(G.transpose(), C), G), _mul(V, G)


@ti.func
def sort_columns(lam, V, p: ti.template(), q: ti.template()):
    """Swap eigenvalues p < q (and V's columns) where lam_p < lam_q, negating one column so that det V stays +1."""
    swap = lam[p] < lam[q]
    lam_sorted = ti.Vector([ti.select(swap, lam[q], lam[p]) if k == p else ti.select(swap, lam[p], lam[q]) if k == q
                            else lam[k] for k in ti.static(range(3))])
    V_sorted = ti.Matrix.cols([ti.select(swap, V[:, q], V[:, p]) if k == p else ti.select(swap, -V[:, p], V[:, q])
                               if k == q else V[:, k] for k in ti.static(range(3))])
    return lam_sorted, V_sorted


@ti.func
def unit_or(a, fallback):
    """a / |a|, or `fallback` where a = 0 (a rank-deficient F: any unit vector completing the frame will do)."""
    n2 = a.dot(a)
    zero = n2 <= 0.0  # guard: a zero column has no direction
    return ti.select(zero, fallback, a / ti.sqrt(ti.select(zero, 1.0, n2)))


@ti.func
def svd_rotation(F):
    """U V^T of the rotation-variant SVD F = U Sigma V^T, s1 >= s2 >= |s3|, s3 with the sign of J, det U = det V = 1.

    V: Jacobi on F^T F, sorted by decreasing eigenvalue. U: Gram-Schmidt on the columns F v1, F v2 and
    u3 = u1 x u2, which makes U a rotation and leaves the sign of J to s3 = u3 . F v3. Accurate to about
    1e-8 relative (squaring F, near-degenerate eigenvectors): polar_rotation polishes it.
    """
    C = _mul(F.transpose(), F)
    V = ti.Matrix.identity(float, 3)
    for _ in ti.static(range(JACOBI_SWEEPS)):
        C, V = jacobi_rotate(C, V, 0, 1)
        C, V = jacobi_rotate(C, V, 0, 2)
        C, V = jacobi_rotate(C, V, 1, 2)
    lam = ti.Vector([C[0, 0], C[1, 1], C[2, 2]])
    lam, V = sort_columns(lam, V, 0, 1)
    lam, V = sort_columns(lam, V, 1, 2)
    lam, V = sort_columns(lam, V, 0, 1)
    u1 = unit_or(_mulv(F, V[:, 0]), ti.Vector([1.0, 0.0, 0.0]))
    a2 = _mulv(F, V[:, 1])
    # u1 nearly e1: e0 is the axis farther from it
    other = ti.select(ti.abs(u1[1]) > 0.9, ti.Vector([1.0, 0.0, 0.0]), ti.Vector([0.0, 1.0, 0.0]))
    u2 = unit_or(a2 - u1.dot(a2) * u1, unit_or(u1.cross(other), other))
    U = ti.Matrix.cols([u1, u2, u1.cross(u2)])
    return _mul(U, V.transpose())


@ti.func
def higham_rotation(F, steps):
    """The orthogonal polar factor of F (J > 0, so a rotation) by Higham's scaled Newton iteration (Higham 1986),
    X <- (z X + X^{-T} / z) / 2 with z = |det X|^(-1/3) (z = 1 in the last step), `steps` (<= HIGHAM_STEPS, less
    higham_fewer) times from X = F; X^{-T} = cof(X) / det X."""
    X = F
    for k in ti.static(range(HIGHAM_STEPS - higham_fewer())):
        if ti.static(k < HIGHAM_MIN_STEPS - higham_fewer() - 1):  # a scaled step in every tier
            X = higham_step(X, True)
        elif k < steps:
            X = higham_step(X, k < steps - 1)
    return X


@ti.func
def inverse_cbrt(a):
    """a^(-1/3) for a > 0. On Vulkan in float64, whose SPIR-V has no 64-bit pow: a float32 pow, then two Newton
    steps y <- y (4 - a y^3) / 3 in float64 (each squares the relative error: 1e-7 -> 1e-14 -> round-off; a must
    lie in float32's normal range, as any det of a simulated F does)."""
    y = a * 0.0
    if ti.static(spirv() and impl.current_cfg().default_fp == ti.f64):
        y = ti.cast(ti.cast(a, ti.f32) ** ti.cast(-1.0 / 3.0, ti.f32), ti.f64)
        for _ in ti.static(range(2)):
            y = y * (4.0 - a * y * y * y) / 3.0
    else:
        y = a ** (-1.0 / 3.0)
    return y


@ti.func
def higham_step(X, scaled):
    """One step of higham_rotation: (z X + cof(X) / (z det X)) / 2, z = |det X|^(-1/3) if scaled, else 1."""
    cX = cofactor(X)
    d = X[:, 0].dot(cX[:, 0])  # det X: stays > 0 (each iterate is F's polar factor times an SPD matrix)
    z = 1.0 + 0.0 * d
    if scaled:
        z = inverse_cbrt(ti.abs(d))
    return 0.5 * (z * X + cX / (z * d))


@ti.func
def higham_steps(q):
    """Higham steps for R at round-off, given q = J / (|F|_F^2 / 3)^(3/2) > HIGHAM_Q (HIGHAM_TIERS; one
    fewer in float32, higham_fewer)."""
    fewer = ti.static(higham_fewer())
    n = HIGHAM_STEPS - fewer
    for t in ti.static(HIGHAM_TIERS[::-1]):
        n = ti.select(q > t[0], t[1] - fewer, n)
    return n


@ti.func
def polar_rotation(F):
    """R of the polar decomposition F = R S, R a proper rotation.

    2D: angle theta = atan2(b, a), a = F00 + F11, b = F10 - F01; cos(theta) = a / r and sin(theta) = b / r with
    r = |(a, b)|: the same R without trigonometry. Where r vanishes the angle is undefined and, like
    atan2(0, 0) = 0, R = I is taken.

    3D: where F is well-conditioned with J > 0 (see HIGHAM_Q), Higham's iteration (higham_rotation) to round-off,
    value and derivative (see HIGHAM_STEPS). Else U V^T of the rotation-variant SVD (svd_rotation), then
    NEWTON_STEPS Newton steps R <- R cay(omega) (newton_rotation) on skew(R^T F) = 0: with S' = R^T F,
    (tr(S) I - S) omega = axial(S' - S'^T), S = sym(S') (rotation_solve). Each step zeroes the first-order error,
    so the result is at round-off and, under ti.ad.Tape, its derivative is the exact dR = R [omega]_x
    (polar_rotation's closed form in adjoint.material.stress_reverse) whatever the derivative of the SVD. Where
    tr(S) I - S is singular R is not unique; the SVD's R is kept.
    """
    if ti.static(F.n == 2):
        a = F[0, 0] + F[1, 1]
        b = F[1, 0] - F[0, 1]
        r2 = a * a + b * b
        c = 1.0 + 0.0 * r2
        s = 0.0 * r2
        if r2 > ROTATION_EPS:  # guard: undefined angle, see ROTATION_EPS
            r = ti.sqrt(r2)
            c = a / r
            s = b / r
        return ti.Matrix([[c, -s], [s, c]])
    else:
        J = F.determinant()
        n2 = (F * F).sum() / 3.0
        R = ti.Matrix.identity(float, 3)
        if J > 0.0 and J * J > HIGHAM_Q * HIGHAM_Q * n2 * n2 * n2:  # well-conditioned, not inverted: see HIGHAM_Q
            R = higham_rotation(F, higham_steps(J / (n2 * ti.sqrt(n2))))
        else:
            R = svd_rotation(F)
            for _ in ti.static(range(NEWTON_STEPS)):
                R = newton_rotation(F, R)
        return R


@ti.func
def newton_rotation(F, R):
    """One Newton step R <- R cay(omega) toward the polar rotation of F (see polar_rotation)."""
    Sp = _mul(R.transpose(), F)
    return _mul(R, cayley(rotation_solve(0.5 * (Sp + Sp.transpose()), axial(Sp - Sp.transpose()))))


@ti.func
def stress(F, mu, lam):
    """First Piola-Kirchhoff stress P(F) = 2 mu (F - R) + lambda (J - 1) J F^{-T} (eq 9, 14)."""
    return rotated_stress(F, polar_rotation(F), mu, lam)


@ti.func
def rotated_stress(F, R, mu, lam):
    """P(F) of eq 9 given R = polar_rotation(F), for a caller that needs R again (the reverse P2G: in 3D the polar
    decomposition is the costliest part of the kernel, to run and to compile)."""
    J = F.determinant()
    return 2.0 * mu * (F - R) + lam * (J - 1.0) * cofactor(F)
