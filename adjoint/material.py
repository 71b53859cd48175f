"""dP(F) : adj_P for fixed-corotated stress (eq 57's d^2 Psi / dF dF : dL/dP), in closed form, in 2D and 3D."""
import taichi as ti

from mls_mpm.material import ROTATION_EPS, _mul, axial, cofactor, cross_matrix, polar_rotation, rotation_solve


@ti.func
def cofactor_adjoint(F, adj_cof):
    """dL/dF of cof(F) = J F^{-T} given adj_cof = dL/dcof (eq 9's volume term).

    2D: cof is linear, its adjoint is cof(adj_cof). 3D: cof(F) has the columns f1 x f2, f2 x f0, f0 x f1, so with
    a_k the columns of adj_cof, sum_k a_k . dcof_k gives the columns a1 x f2 + f1 x a2, a2 x f0 + f2 x a0,
    a0 x f1 + f0 x a1 (a x b . c = b x c . a); this is cof(F + A) - cof(F) - cof(A), bilinear, not cof(A).
    """
    if ti.static(F.n == 2):
        return cofactor(adj_cof)
    else:
        f0, f1, f2 = F[:, 0], F[:, 1], F[:, 2]
        a0, a1, a2 = adj_cof[:, 0], adj_cof[:, 1], adj_cof[:, 2]
        return ti.Matrix.cols([a1.cross(f2) + f1.cross(a2), a2.cross(f0) + f2.cross(a0), a0.cross(f1) + f0.cross(a1)])


@ti.func
def rotation_adjoint(F, adj_P, mu):
    """dL/dF through R(F) in the term -2 mu R of P (eq 9; eq 57, second term), adj_R = -2 mu adj_P.

    2D: R(theta), theta = atan2(b, a) with a = F00 + F11, b = F10 - F01, so
    dtheta = (a db - b da) / (a^2 + b^2) and dL/dtheta = -2 mu (dR/dtheta : adj_P).

    3D: with F = R S (S symmetric) and dR = R [omega]_x, R^T dF - dF^T R = [omega] S + S [omega], whose axial
    vector is M omega, M = tr(S) I - S (symmetric; eigenvalues s2 + s3, s1 + s3, s1 + s2 in the rotation-variant
    SVD). Then dL = adj_R : R [omega] = axial(B - B^T) . omega with B = R^T adj_R, so with y = M^{-1} axial(B - B^T)
    dL = y . axial(R^T dF - dF^T R) = (1/2) [y] : (R^T dF - dF^T R) = R [y] : dF, and dL/dF = R [y]_x.
    M is regular where singular values repeat (F = a I: M = 2a I), so those gradients are exact; where M is
    singular (two singular values sum to zero: R is not unique) rotation_solve returns 0 and, as in 2D, the
    rotation term's derivative is taken as zero.
    """
    R = polar_rotation(F)
    adj_F = 0.0 * F
    if ti.static(F.n == 2):
        a = F[0, 0] + F[1, 1]
        b = F[1, 0] - F[0, 1]
        r2 = a * a + b * b
        c = R[0, 0]
        s = R[1, 0]
        # dR/dtheta = [[-s, -c], [c, -s]]
        adj_theta = -2.0 * mu * (-s * adj_P[0, 0] - c * adj_P[0, 1] + c * adj_P[1, 0] - s * adj_P[1, 1])
        adj_a = 0.0 * r2
        adj_b = 0.0 * r2
        if r2 > ROTATION_EPS:  # guard: singular polar angle, the rotation term's derivative is taken as zero
            adj_a = -adj_theta * b / r2  # dL/da
            adj_b = adj_theta * a / r2  # dL/db
        adj_F = ti.Matrix([[adj_a, -adj_b], [adj_b, adj_a]])
    else:
        Sp = _mul(R.transpose(), F)
        B = -2.0 * mu * _mul(R.transpose(), adj_P)
        y = rotation_solve(0.5 * (Sp + Sp.transpose()), axial(B - B.transpose()))
        adj_F = _mul(R, cross_matrix(y))
    return adj_F


@ti.func
def stress_reverse(F, adj_P, mu, lam):
    """Return dL/dF given adj_P = dL/dP for P = 2 mu (F - R) + lambda (J - 1) cof(F) (eq 9; eq 57, second term).

    Rotation: rotation_adjoint (2D through the polar angle, 3D through dR = R [omega]_x).
    Volume: d[(J - 1) cof(F)] : adj_P = (cof(F) : adj_P) cof(F) + (J - 1) dcof^T[adj_P], since dJ/dF = cof(F);
    dcof^T is cofactor_adjoint (cof(adj_P) in 2D, bilinear in F and adj_P in 3D).
    """
    cF = cofactor(F)
    J = F.determinant()
    adj_F = 2.0 * mu * adj_P + lam * (cF * adj_P).sum() * cF + lam * (J - 1.0) * cofactor_adjoint(F, adj_P)
    adj_F += rotation_adjoint(F, adj_P, mu)
    return adj_F
