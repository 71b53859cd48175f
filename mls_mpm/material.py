"""Fixed-corotated elasticity (eq 9) with a closed-form 2D polar rotation."""
import taichi as ti


@ti.func
def cofactor(F):
    """J F^{-T} written without a division, so J -> 0 is harmless."""
    return ti.Matrix([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])


@ti.func
def polar_rotation(F):
    """R of the polar decomposition F = R S: angle theta = atan2(F10 - F01, F00 + F11).

    Where F is symmetric with zero trace the angle is undefined; atan2(0, 0) = 0 picks R = I.
    """
    theta = ti.atan2(F[1, 0] - F[0, 1], F[0, 0] + F[1, 1])
    c = ti.cos(theta)
    s = ti.sin(theta)
    return ti.Matrix([[c, -s], [s, c]])


@ti.func
def stress(F, mu, lam):
    """First Piola-Kirchhoff stress P(F) = 2 mu (F - R) + lambda (J - 1) J F^{-T} (eq 9, 14)."""
    R = polar_rotation(F)
    J = F.determinant()
    return 2.0 * mu * (F - R) + lam * (J - 1.0) * cofactor(F)
