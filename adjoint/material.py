"""dP(F) : G for fixed-corotated stress (eq 57's d^2 Psi / dF dF : dL/dP), in closed form."""
import taichi as ti

from mls_mpm.material import ROTATION_EPS, cofactor, polar_rotation


@ti.func
def stress_reverse(F, G, mu, lam):
    """Return dL/dF given G = dL/dP for P = 2 mu (F - R) + lambda (J - 1) cof(F).

    Rotation: R(theta), theta = atan2(b, a) with a = F00 + F11, b = F10 - F01, so
    dtheta = (a db - b da) / (a^2 + b^2) and dL/dtheta = -2 mu (dR/dtheta : G).
    Volume: d[(J - 1) cof(F)] : G = (cof(F) : G) cof(F) + (J - 1) cof(G), since dJ/dF = cof(F)
    and cof is linear with adjoint cof(G).
    """
    a = F[0, 0] + F[1, 1]
    b = F[1, 0] - F[0, 1]
    r2 = a * a + b * b
    R = polar_rotation(F)
    c = R[0, 0]
    s = R[1, 0]
    # dR/dtheta = [[-s, -c], [c, -s]]
    g_theta = -2.0 * mu * (-s * G[0, 0] - c * G[0, 1] + c * G[1, 0] - s * G[1, 1])
    k_a = 0.0 * r2
    k_b = 0.0 * r2
    if r2 > ROTATION_EPS:  # guard: singular polar angle, the rotation term's derivative is taken as zero
        k_a = -g_theta * b / r2  # dL/da
        k_b = g_theta * a / r2  # dL/db
    cF = cofactor(F)
    J = F.determinant()
    dF = 2.0 * mu * G + lam * (cF * G).sum() * cF + lam * (J - 1.0) * cofactor(G)
    dF += ti.Matrix([[k_a, -k_b], [k_b, k_a]])
    return dF
