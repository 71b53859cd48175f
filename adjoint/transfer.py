"""Reverse G2P (eq 47-48, 66-69) and reverse P2G (eq 54-65, 71) for one step f."""
import taichi as ti

from mls_mpm.kernels import inside, node_weight, stencil, weights
from mls_mpm.material import stress
from mls_mpm.transfer import affine_momentum, control_sum

from .material import stress_reverse


@ti.func
def scatter_adj_v(s: ti.template(), a: ti.template(), lane, i, j, g):
    """dL/dv_i += g, or into this thread's private grid `lane` (see mls_mpm.transfer.scatter_node)."""
    if ti.static(s.lanes > 0):
        a.lane_adj_v[lane, i, j] = a.lane_adj_v[lane, i, j] + g
    else:
        a.adj_grid_v[i, j] += g


@ti.func
def g2p_reverse_particle(s: ti.template(), a: ti.template(), f, p, lane):
    """From dL/d(x, v, C, F) of step f + 1 (slot (f+1) % 2): dL/dv_i^f and the G2P part of dL/dx_p^f, dL/dF_p^f.

    With g_v = dL/dv^{n+1} + dt dL/dx^{n+1} (eq 21) and g_C = dL/dC^{n+1} + dt dL/dF^{n+1} (F + F_pc)^T (eq 20):
    dL/dv_i += N g_v + 3/dx^2 N g_C (x_i - x_p)  (eq 48)
    dL/dx_p += dL/dx^{n+1} + sum_i dN (v_i . g_v) + 3/dx^2 [dN (g_C : v_i dpos^T) - N g_C^T v_i]  (eq 66-69)
    dL/d(F + F_pc) += (I + dt C^{n+1})^T dL/dF^{n+1}  (eq 57, first term)
    """
    x = s.x[f, p]
    base, fx = stencil(x, s.inv_dx)
    if inside(base, s.n_grid):
        src = (f + 1) % 2
        dst = f % 2
        w, dw = weights(fx)
        Fs = control_sum(s, f, p)
        g_x = a.adj_x[src, p]
        g_F = a.adj_F[src, p]
        g_v = a.adj_v[src, p] + s.dt * g_x
        g_C = a.adj_C[src, p] + s.dt * g_F @ Fs.transpose()
        k = 3.0 * s.inv_dx * s.inv_dx
        adj_x = g_x
        sum_v = ti.Vector.zero(float, 2)  # sum_i N v_i
        for i, j in ti.static(ti.ndrange(4, 4)):
            N, dN = node_weight(w, dw, ti.Vector([i, j]), s.inv_dx)
            dpos = (ti.Vector([i, j]) - fx) * s.dx
            v_i = s.grid_v[f, base[0] + i, base[1] + j]
            scatter_adj_v(s, a, lane, base[0] + i, base[1] + j, N * (g_v + k * g_C @ dpos))
            adj_x += dN * v_i.dot(g_v + k * g_C @ dpos)  # g_C : v_i dpos^T = v_i . g_C dpos
            sum_v += N * v_i
        adj_x -= k * g_C.transpose() @ sum_v
        a.adj_x[dst, p] += adj_x
        a.adj_F[dst, p] += (ti.Matrix.identity(float, 2) + s.dt * s.C[f + 1, p]).transpose() @ g_F


@ti.func
def p2g_reverse_particle(s: ti.template(), a: ti.template(), f, p):
    """From dL/dm_i, dL/dp_i of grid f: the P2G part of dL/d(x, v, C, F)_p^f, and dL/dF_pc of control f / stride.

    dL/dv_p += sum_i N m_p (1 - dt gamma) dL/dp_i  (eq 71)
    dL/dC_p += m_p sum_i N dL/dp_i dpos^T  (eq 60)
    dL/dx_p += sum_i dN [m_p dL/dm_i + dL/dp_i . (m_p v_p (1 - dt gamma) + G dpos)] - N G^T dL/dp_i  (eq 64-65)
    dL/dG = sum_i N dL/dp_i dpos^T; with A = P (F + F_pc)^T and G = -3/dx^2 dt V^0 A + m_p C:
    dL/d(F + F_pc) += dL/dA^T P + dP/dF : (dL/dA (F + F_pc))  (eq 54, 57-58)
    Then dL/dF_pc^k += dL/dF_p^f when f = k * stride (eq 55), so g2p_reverse must run first.
    """
    x = s.x[f, p]
    base, fx = stencil(x, s.inv_dx)
    if inside(base, s.n_grid):
        dst = f % 2
        w, dw = weights(fx)
        Fs = control_sum(s, f, p)
        G = affine_momentum(s, f, p, Fs)
        drag = s.m_p * (1.0 - s.dt * s.gamma)
        mv = drag * s.v[f, p]
        adj_x = ti.Vector.zero(float, 2)
        sum_g_p = ti.Vector.zero(float, 2)  # sum_i N dL/dp_i
        adj_G = ti.Matrix.zero(float, 2, 2)
        for i, j in ti.static(ti.ndrange(4, 4)):
            N, dN = node_weight(w, dw, ti.Vector([i, j]), s.inv_dx)
            dpos = (ti.Vector([i, j]) - fx) * s.dx
            g_m = a.adj_grid_m[base[0] + i, base[1] + j]
            g_p = a.adj_grid_p[base[0] + i, base[1] + j]
            adj_x += dN * (s.m_p * g_m + g_p.dot(mv + G @ dpos))
            sum_g_p += N * g_p
            adj_G += N * g_p.outer_product(dpos)
        adj_x -= G.transpose() @ sum_g_p
        adj_v = drag * sum_g_p
        adj_A = -3.0 * s.inv_dx * s.inv_dx * s.dt * s.vol * adj_G
        P = stress(Fs, s.mu, s.lam)
        adj_Fs = adj_A.transpose() @ P + stress_reverse(Fs, adj_A @ Fs, s.mu, s.lam)
        a.adj_x[dst, p] += adj_x
        a.adj_v[dst, p] += adj_v
        a.adj_C[dst, p] += s.m_p * adj_G
        a.adj_F[dst, p] += adj_Fs
        if f % s.stride == 0:
            a.adj_F_pc[f // s.stride, p] += a.adj_F[dst, p]


@ti.kernel
def g2p_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse G2P of step f (twin of mls_mpm.transfer.g2p)."""
    for p in range(s.n_particles):
        g2p_reverse_particle(s, a, f, p, 0)


@ti.kernel
def p2g_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse P2G of step f (twin of mls_mpm.transfer.p2g)."""
    for p in range(s.n_particles):
        p2g_reverse_particle(s, a, f, p)
