"""Fixed-corotated elasticity (eq 9) with a closed-form 2D polar rotation."""
import taichi as ti


@ti.func
def cofactor(F):
    """J F^{-T} written without a division, so J -> 0 is harmless."""
    return ti.Matrix([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])


# Below this squared norm of (F00 + F11, F10 - F01) the polar angle is undefined (F symmetric with zero trace).
ROTATION_EPS = 1e-20


@ti.func
def polar_rotation(F):
    """R of the polar decomposition F = R S: angle theta = atan2(b, a), a = F00 + F11, b = F10 - F01.

    cos(theta) = a / r and sin(theta) = b / r with r = |(a, b)|: the same R without trigonometry.
    Where r vanishes the angle is undefined and, like atan2(0, 0) = 0, R = I is taken.
    """
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


@ti.func
def stress(F, mu, lam):
    """First Piola-Kirchhoff stress P(F) = 2 mu (F - R) + lambda (J - 1) J F^{-T} (eq 9, 14)."""
    R = polar_rotation(F)
    J = F.determinant()
    return 2.0 * mu * (F - R) + lam * (J - 1.0) * cofactor(F)
