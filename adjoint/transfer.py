"""Reverse G2P (eq 47-48, 66-69), reverse P2G (eq 54-65, 71) and the adjoint's fault check for one step f."""
import taichi as ti

from mls_mpm.config import STENCIL
from mls_mpm.grid import velocity_slot
from mls_mpm.kernels import (along_slab, axis0_column, inside, join, node_N, outer_row, outer_slab, roll, row_offsets,
                             slab_dN, slab_dN_add, slab_offsets, stencil, weights)
from mls_mpm.material import polar_rotation, rotated_stress
from mls_mpm.sizes import n_live
from mls_mpm.state import unpack_mp
from mls_mpm.transfer import affine_momentum, control_sum

from .material import rotated_stress_reverse
from .state import add_own


@ti.func
def scatter_adj_node(s: ti.template(), a: ti.template(), lane, I, adj_v):
    """dL/dv_i += adj_v at node I, or into this thread's private grid `lane` (as mls_mpm.transfer.scatter_node)."""
    if ti.static(s.lanes > 0):
        add_own(a.lane_adj_v, lane, I, adj_v)
    else:
        a.adj_grid_v[I] += adj_v


@ti.func
def g2p_particle_reverse(s: ti.template(), a: ti.template(), f, p, lane, adj_x_next, adj_v_next, adj_C_next,
                         adj_F_next):
    """From dL/d(x, v, C, F)_p of step f + 1: dL/dv_i^f (scattered) and the G2P parts of dL/dx_p^f, dL/dF_p^f
    (returned; zero for a particle whose stencil leaves the grid, which G2P skips). G2P reads neither v^f nor C^f.

    With adj_v_new = dL/dv^{n+1} + dt dL/dx^{n+1} (eq 21) and adj_C_new = dL/dC^{n+1} + dt dL/dF^{n+1} (F + F_pc)^T
    (eq 20), the adjoints of G2P's v_new and C_new:
    dL/dv_i += N adj_v_new + 3/dx^2 N adj_C_new (x_i - x_p)  (eq 48)
    dL/dx_p += dL/dx^{n+1} + sum_i dN (v_i . adj_v_new) + 3/dx^2 [dN (adj_C_new : v_i dpos^T) - N adj_C_new^T v_i]
        (eq 66-69)
    dL/d(F + F_pc) += (I + dt C^{n+1})^T dL/dF^{n+1}  (eq 57, first term)
    The last term of dL/dx_p, -3/dx^2 adj_C_new^T sum_i N v_i, takes sum_i N v_i = v^{n+1} as the forward stored it
    (eq 18): the stencil loop then carries no sum of its own (3D: the loop 1.3x faster, kernel profiler).
    """
    x = s.x[f, p]
    base, fx = stencil(x, s.inv_dx)
    adj_x = ti.Vector.zero(float, s.dim)
    adj_F = ti.Matrix.zero(float, s.dim, s.dim)
    if inside(base, s.n_grid):
        w, dw = weights(fx)
        Fs = control_sum(s, f, p)
        adj_v_new = adj_v_next + s.dt * adj_x_next
        adj_C_new = adj_C_next + s.dt * adj_F_next @ Fs.transpose()
        k = 3.0 * s.inv_dx * s.inv_dx
        adj_x = adj_x_next
        w0, dw0 = axis0_column(w), axis0_column(dw)
        for i0 in range(STENCIL):  # the stencil's outer loop, a runtime loop: see mls_mpm.kernels
            adj_x = g2p_slab_reverse(s, a, f, lane, base, fx, w0[0], dw0[0], w, dw, adj_v_new, adj_C_new, i0, adj_x)
            w0, dw0 = roll(w0), roll(dw0)
        adj_x -= k * adj_C_new.transpose() @ s.v[f + 1, p]  # v^{n+1} = sum_i N v_i (eq 18), stored by the forward
        adj_F = (ti.Matrix.identity(float, s.dim) + s.dt * s.C[f + 1, p]).transpose() @ adj_F_next
    return adj_x, adj_F


@ti.func
def g2p_slab_reverse(s: ti.template(), a: ti.template(), f, lane, base, fx, w0, dw0, w, dw, adj_v_new, adj_C_new, i0,
                     adj_x):
    """Slab i0 of g2p_particle_reverse (w0, dw0: its axis-0 weights w[i0, 0], dw[i0, 0]): dL/dv_i of its nodes
    (eq 48), and their sum_i dN terms of dL/dx_p (eq 66-69), added to adj_x."""
    M = 3.0 * s.inv_dx * adj_C_new  # 3/dx^2 adj_C_new (x_i - x_p) = M (o - fx): kernels.along_slab
    a0 = adj_v_new - M @ (fx - 1.0) + (i0 - 1) * M[:, 0]  # at node (i0, 1, ..)
    acc = ti.Vector.zero(float, s.dim)  # slab_dN_add's sums
    for o2 in ti.static(slab_offsets(s.dim)):
        o = join(i0, o2)
        N = node_N(w0, w, o2)
        v_i = s.grid_v[velocity_slot(s, f), base + o]
        adj_v_i = along_slab(a0, M, o2)  # adj_v_new + 3/dx^2 adj_C_new (x_i - x_p)
        scatter_adj_node(s, a, lane, base + o, N * adj_v_i)
        acc = slab_dN_add(acc, w, dw, o2, v_i.dot(adj_v_i))  # adj_C_new : v_i dpos^T = v_i . adj_C_new dpos
    return adj_x + slab_dN(acc, w0, dw0, s.inv_dx)


@ti.func
def p2g_particle_reverse(s: ti.template(), a: ti.template(), f, p):
    """From dL/dm_i, dL/dp_i of grid f: the P2G parts of dL/d(x, v, C, F)_p^f, returned (zero for a particle whose
    stencil leaves the grid, which P2G skips).

    dL/dv_p += sum_i N m_p (1 - dt gamma) dL/dp_i  (eq 71)
    dL/dC_p += m_p sum_i N dL/dp_i dpos^T  (eq 60)
    dL/dx_p += sum_i dN [m_p dL/dm_i + dL/dp_i . (m_p v_p (1 - dt gamma) + G dpos)] - N G^T dL/dp_i  (eq 64-65)
    dL/dG = sum_i N dL/dp_i dpos^T; with A = P (F + F_pc)^T and G = -3/dx^2 dt V^0 A + m_p C:
    dL/d(F + F_pc) += dL/dA^T P + dP/dF : (dL/dA (F + F_pc))  (eq 54, 57-58)
    The caller adds the G2P part and then dL/dF_pc^k += dL/dF_p^f when f = k * stride (eq 55).
    """
    x = s.x[f, p]
    base, fx = stencil(x, s.inv_dx)
    adj_x = ti.Vector.zero(float, s.dim)
    adj_v = ti.Vector.zero(float, s.dim)
    adj_C = ti.Matrix.zero(float, s.dim, s.dim)
    adj_Fs = ti.Matrix.zero(float, s.dim, s.dim)
    if inside(base, s.n_grid):
        w, dw = weights(fx)
        Fs = control_sum(s, f, p)
        R = polar_rotation(Fs)  # once: the stress, G and the stress's reverse all need it
        P = rotated_stress(Fs, R, s.mu, s.lam)
        G = affine_momentum(s, f, p, Fs, P)
        drag = s.m_p * (1.0 - s.dt * s.gamma)
        mv = drag * s.v[f, p]
        sum_adj_p = ti.Vector.zero(float, s.dim)  # sum_i N dL/dp_i
        Q = ti.Matrix.zero(float, s.dim, s.dim)  # sum_i N dL/dp_i (o - 1)^T
        w0, dw0 = axis0_column(w), axis0_column(dw)
        for i0 in range(STENCIL):  # the stencil's outer loop, a runtime loop: see mls_mpm.kernels
            adj_x, sum_adj_p, Q = p2g_slab_reverse(s, a, base, fx, w0[0], dw0[0], w, dw, G, mv, i0, adj_x, sum_adj_p, Q)
            w0, dw0 = roll(w0), roll(dw0)
        adj_G = s.dx * (Q - sum_adj_p.outer_product(fx - 1.0))  # sum_i N dL/dp_i (x_i - x_p)^T (eq 60)
        adj_x -= G.transpose() @ sum_adj_p
        adj_v = drag * sum_adj_p
        adj_A = -3.0 * s.inv_dx * s.inv_dx * s.dt * s.vol * adj_G
        adj_Fs = adj_A.transpose() @ P + rotated_stress_reverse(Fs, R, adj_A @ Fs, s.mu, s.lam)
        adj_C = s.m_p * adj_G
    return adj_x, adj_v, adj_C, adj_Fs


@ti.func
def p2g_slab_reverse(s: ti.template(), a: ti.template(), base, fx, w0, dw0, w, dw, G, mv, i0, adj_x, sum_adj_p, Q):
    """Slab i0 of p2g_particle_reverse (w0, dw0: its axis-0 weights w[i0, 0], dw[i0, 0]): its nodes' terms of dL/dx_p
    (eq 64-65), of sum_i N dL/dp_i and of sum_i N dL/dp_i (o - 1)^T (Q: dL/dG's sum, see mls_mpm.kernels.outer_slab).
    mv + G (x_i - x_p) as in mls_mpm.transfer.p2g_slab."""
    Gdx = G * s.dx
    a0 = mv - Gdx @ (fx - 1.0) + (i0 - 1) * Gdx[:, 0]
    slab = ti.Vector.zero(float, s.dim)
    acc = ti.Vector.zero(float, s.dim)  # slab_dN_add's sums
    for o1 in ti.static(row_offsets(s.dim)):
        row = ti.Vector.zero(float, s.dim)
        for k in ti.static(range(STENCIL)):
            o2 = ti.static(o1 + (k,))
            o = join(i0, o2)
            N = node_N(w0, w, o2)
            adj_p_i, adj_m_i = unpack_mp(a.adj_grid_mp[base + o])
            acc = slab_dN_add(acc, w, dw, o2, s.m_p * adj_m_i + adj_p_i.dot(along_slab(a0, Gdx, o2)))
            Np = N * adj_p_i
            row += Np
            Q = outer_row(Q, Np, k)
        slab += row
        Q = outer_slab(Q, row, o1)
    for r in ti.static(range(s.dim)):
        Q[r, 0] += (i0 - 1) * slab[r]
    return adj_x + slab_dN(acc, w0, dw0, s.inv_dx), sum_adj_p + slab, Q


@ti.func
def record_fault_reverse(s: ti.template(), a: ti.template(), f, p):
    """Keep the latest reverse step f with a non-finite adjoint, and in it the lowest particle p.

    Stored as the largest f * N + (N - 1 - p) (atomic_max: the same under any parallel order); the reverse
    pass runs f downward, so the latest step is where the adjoint first went non-finite.
    """
    N = ti.cast(n_live(s), ti.i64)
    ti.atomic_max(a.fault[None], ti.cast(f, ti.i64) * N + (N - 1 - p))


@ti.func
def check_particle_reverse(s: ti.template(), a: ti.template(), f, p, adj_x, adj_v, adj_C, adj_F):
    """Record particle p if its adjoint dL/d(x, v, C, F)_p^f holds NaN or Inf (twin of
    mls_mpm.transfer.check_particle)."""
    total = adj_x.sum() + adj_v.sum() + adj_C.sum() + adj_F.sum()
    if ti.math.isnan(total) or ti.math.isinf(total):
        record_fault_reverse(s, a, f, p)


@ti.kernel
def g2p_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse G2P of step f (twin of mls_mpm.transfer.g2p): dL/d(x, v, C, F) of step f + 1 from slot (f + 1) % 2,
    its G2P parts added to slot f % 2 (the reverse pass itself keeps them in registers: adjoint.step)."""
    for p in range(n_live(s)):
        src, dst = (f + 1) % 2, f % 2
        adj_x, adj_F = g2p_particle_reverse(s, a, f, p, 0, a.adj_x[src, p], a.adj_v[src, p], a.adj_C[src, p],
                                            a.adj_F[src, p])
        add_own(a.adj_x, dst, p, adj_x)  # particle p's own entries: state.add_own, not atomic adds
        add_own(a.adj_F, dst, p, adj_F)


@ti.kernel
def p2g_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Reverse P2G of step f (twin of mls_mpm.transfer.p2g): its parts added to slot f % 2, then, at a control
    step, dL/dF_pc^k += dL/dF_p^f (eq 55) for a particle on the grid (slot f % 2 standing for the whole adjoint)."""
    for p in range(n_live(s)):
        dst = f % 2
        adj_x, adj_v, adj_C, adj_F = p2g_particle_reverse(s, a, f, p)
        add_own(a.adj_x, dst, p, adj_x)
        add_own(a.adj_v, dst, p, adj_v)
        add_own(a.adj_C, dst, p, adj_C)
        add_own(a.adj_F, dst, p, adj_F)
        if f % s.stride == 0 and inside(stencil(s.x[f, p], s.inv_dx)[0], s.n_grid):
            add_own(a.adj_F_pc, f // s.stride, p, a.adj_F[dst, p])
