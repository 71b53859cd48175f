"""dP(F) : adj_P for fixed-corotated stress (eq 57's d^2 Psi / dF dF : dL/dP), in closed form."""
import taichi as ti

from mls_mpm.material import ROTATION_EPS, cofactor, polar_rotation


@ti.func
def stress_reverse(F, adj_P, mu, lam):
    """Return dL/dF given adj_P = dL/dP for P = 2 mu (F - R) + lambda (J - 1) cof(F) (eq 57, second term).

    Rotation: R(theta), theta = atan2(b, a) with a = F00 + F11, b = F10 - F01, so
    dtheta = (a db - b da) / (a^2 + b^2) and dL/dtheta = -2 mu (dR/dtheta : adj_P).
    Volume: d[(J - 1) cof(F)] : adj_P = (cof(F) : adj_P) cof(F) + (J - 1) cof(adj_P), since dJ/dF = cof(F)
    and cof is linear with adjoint cof(adj_P).
    """
    a = F[0, 0] + F[1, 1]
    b = F[1, 0] - F[0, 1]
    r2 = a * a + b * b
    R = polar_rotation(F)
    c = R[0, 0]
    s = R[1, 0]
    # dR/dtheta = [[-s, -c], [c, -s]]
    adj_theta = -2.0 * mu * (-s * adj_P[0, 0] - c * adj_P[0, 1] + c * adj_P[1, 0] - s * adj_P[1, 1])
    adj_a = 0.0 * r2
    adj_b = 0.0 * r2
    if r2 > ROTATION_EPS:  # guard: singular polar angle, the rotation term's derivative is taken as zero
        adj_a = -adj_theta * b / r2  # dL/da
        adj_b = adj_theta * a / r2  # dL/db
    cF = cofactor(F)
    J = F.determinant()
    adj_F = 2.0 * mu * adj_P + lam * (cF * adj_P).sum() * cF + lam * (J - 1.0) * cofactor(adj_P)
    adj_F += ti.Matrix([[adj_a, -adj_b], [adj_b, adj_a]])
    return adj_F
