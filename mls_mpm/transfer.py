"""Particle-to-grid (eq 14-16) and grid-to-particle (eq 18-21) transfers for one step f.

A particle whose stencil leaves the grid is skipped (never indexed outside it) and reported by check_particle.
"""
import taichi as ti

from .config import STENCIL
from .grid import velocity_slot
from .kernels import (along_slab, axis0, carry, inside, join, node_N, outer_row, outer_slab, row_offsets, slab_offsets,
                      stencil, weights)
from .material import stress
from .sizes import n_live
from .state import FAULT_LEFT_GRID, FAULT_NON_FINITE, pack_mp


@ti.func
def record_fault(s: ti.template(), kind: ti.template(), f, p):
    """Keep the least faulty f * N + p: the earliest step that had one, and in it the lowest particle index.

    atomic_min makes the report the same under any parallel order. check_particle (the only caller) runs in
    the production step kernels and check_step, never under ti.ad.Tape (which runs p2g, grid_op, g2p).
    """
    ti.atomic_min(s.fault[kind], ti.cast(f, ti.i64) * ti.cast(n_live(s), ti.i64) + p)


@ti.func
def control_sum(s: ti.template(), f, p):
    """F_p^n + F_pc^n (eq 8, 14): control k acts at step k * stride only."""
    Fs = s.F[f, p]
    if f % s.stride == 0:
        Fs += s.F_pc[f // s.stride, p]
    return Fs


@ti.func
def affine_momentum(s: ti.template(), f, p, Fs, P):
    """G_p^n = -3/dx^2 dt V_p^0 P(F + F_pc) (F + F_pc)^T + m_p C_p^n (eq 61), given P = P(F + F_pc)."""
    return -3.0 * s.inv_dx * s.inv_dx * s.dt * s.vol * P @ Fs.transpose() + s.m_p * s.C[f, p]


@ti.func
def scatter_node(s: ti.template(), f, lane, I, dm, dp):
    """m_i += dm, p_i += dp at node I of grid f, or of this thread's private grid `lane` (plain adds, no atomics).

    A private grid holds (p_i, m_i) in one vector per node, adjacent in memory: one read-add-write of dim + 1 values
    a node (the 3D scatter loop measured 1.2x faster than with m_i and p_i in fields of their own)."""
    if ti.static(s.lanes > 0):
        s.lane_mp[lane, I] = s.lane_mp[lane, I] + pack_mp(dp, dm)
    else:
        s.grid_mp[f, I] += pack_mp(dp, dm)


@ti.func
def particle_G(s: ti.template(), f, p):
    """G_p of eq 61 for particle p of step f (its stress at F + F_pc), zero for a particle whose stencil leaves the
    grid: what p2g_particle scatters and the step's check_particle tests, evaluated once per particle and step."""
    on = inside(stencil(s.x[f, p], s.inv_dx)[0], s.n_grid)
    Fs = control_sum(s, f, p)
    return ti.select(on, affine_momentum(s, f, p, Fs, stress(Fs, s.mu, s.lam)), ti.Matrix.zero(float, s.dim, s.dim))


@ti.func
def p2g_particle(s: ti.template(), f, p, lane, G):
    """Scatter particle p of step f onto its 4^dim nodes: m_i += N m_p (eq 15), p_i += N [m_p v_p (1 - dt gamma) + G_p dpos] (eq 16).

    G: particle_G(s, f, p), returned for the step's check_particle.
    """
    base, fx = stencil(s.x[f, p], s.inv_dx)
    on = inside(base, s.n_grid)
    w, _ = weights(fx)
    mv = s.m_p * (1.0 - s.dt * s.gamma) * s.v[f, p]
    if ti.static(s.dim == 2):  # the stencil's outer loop: see kernels.slab_offsets
        if on:
            for i0 in ti.static(range(STENCIL)):
                p2g_slab(s, f, lane, base, fx, w, G, mv, i0)
    else:
        # 3D, in the form the Tape oracle needs (tests/test_tape3d.py): the runtime loop runs no rows for a particle
        # off the grid (the same loop inside `if on` came out wrong under the Tape), and each value read in the
        # loop is carried (kernels.carry)
        for i0 in range(ti.select(on, STENCIL, 0)):
            fx = carry(fx)
            w = carry(w)
            G = carry(G)
            mv = carry(mv)
            p2g_slab(s, f, lane, base, fx, w, G, mv, i0)
    return G


@ti.func
def p2g_slab(s: ti.template(), f, lane, base, fx, w, G, mv, i0):
    """The scatter of p2g_particle onto slab i0 of the stencil: mv + G (x_i - x_p), x_i - x_p = (o - fx) dx, as
    kernels.along_slab from its value at (i0, 0, ..)."""
    Gdx = G * s.dx
    a = mv - Gdx @ (fx - 1.0) + (i0 - 1) * Gdx[:, 0]  # at node (i0, 1, ..)
    w0 = axis0(w, i0)
    for o2 in ti.static(slab_offsets(s.dim)):
        o = join(i0, o2)
        N = node_N(w0, w, o2)
        scatter_node(s, f, lane, base + o, N * s.m_p, N * along_slab(a, Gdx, o2))


@ti.func
def g2p_particle(s: ti.template(), f, p):
    """Gather particle p of step f + 1 from the grid velocities of step f (eq 18-21)."""
    x = s.x[f, p]
    base, fx = stencil(x, s.inv_dx)
    on = inside(base, s.n_grid)
    w, _ = weights(fx)
    v_new = ti.Vector.zero(float, s.dim)
    Q = ti.Matrix.zero(float, s.dim, s.dim)  # sum_i N v_i (o - 1)^T
    if ti.static(s.dim == 2):  # the stencil's outer loop: see kernels.slab_offsets
        if on:
            for i0 in ti.static(range(STENCIL)):
                v_new, Q = g2p_slab(s, f, base, w, i0, v_new, Q)
    else:  # 3D: as in p2g_particle, no rows for a particle off the grid, and the loop's inputs carried
        for i0 in range(ti.select(on, STENCIL, 0)):
            w = carry(w)
            v_new, Q = g2p_slab(s, f, base, w, i0, v_new, Q)
    # eq 19: C = 3/dx^2 sum_i N v_i (x_i - x_p)^T = 3/dx (sum_i N v_i (o - 1)^T - v_new (fx - 1)^T)
    C_new = 3.0 * s.inv_dx * (Q - v_new.outer_product(fx - 1.0))
    if on:
        F_new = (ti.Matrix.identity(float, s.dim) + s.dt * C_new) @ control_sum(s, f, p)  # eq 20
        x_new = x + s.dt * v_new  # eq 21
        s.v[f + 1, p] = v_new
        s.C[f + 1, p] = C_new
        s.F[f + 1, p] = F_new
        s.x[f + 1, p] = x_new


@ti.func
def g2p_slab(s: ti.template(), f, base, w, i0, v_new, Q):
    """The gather of g2p_particle from slab i0 of the stencil: sum_i N v_i added to v_new (eq 18), and
    sum_i N v_i (o - 1)^T (o the node's offset in the stencil) to Q (eq 19's sum, see kernels.outer_slab)."""
    slab = ti.Vector.zero(float, s.dim)
    w0 = axis0(w, i0)
    for o1 in ti.static(row_offsets(s.dim)):  # rows along the last axis: kernels.row_offsets
        row = ti.Vector.zero(float, s.dim)
        for k in ti.static(range(STENCIL)):
            o2 = ti.static(o1 + (k,))
            Nv = node_N(w0, w, o2) * s.grid_v[velocity_slot(s, f), base + join(i0, o2)]
            row += Nv
            Q = outer_row(Q, Nv, k)
        slab += row
        Q = outer_slab(Q, row, o1)
    for r in ti.static(range(s.dim)):
        Q[r, 0] += (i0 - 1) * slab[r]
    return v_new + slab, Q


@ti.func
def check_particle(s: ti.template(), f, p, G):
    """Record particle p of step f if its stencil leaves the grid or its state is not finite.

    G: the G_p that p2g_particle returned for step f < N_t (so that an overflowing control is named at its
    source, the stress), or zero for the last step, which has no P2G. Kept apart from p2g/g2p (which skip such
    a particle) so that those stay differentiable by Taichi.
    """
    total = s.x[f, p].sum() + s.v[f, p].sum() + s.C[f, p].sum() + s.F[f, p].sum() + G.sum()
    if ti.math.isnan(total) or ti.math.isinf(total):  # NaN or Inf anywhere in the particle's state
        record_fault(s, FAULT_NON_FINITE, f, p)
    else:
        base, _ = stencil(s.x[f, p], s.inv_dx)
        if not inside(base, s.n_grid):
            record_fault(s, FAULT_LEFT_GRID, f, p)


@ti.kernel
def p2g(s: ti.template(), f: ti.i32):
    """P2G of step f into grid f (the grid of step f must be zero)."""
    for p in range(n_live(s)):
        p2g_particle(s, f, p, 0, particle_G(s, f, p))


@ti.kernel
def g2p(s: ti.template(), f: ti.i32):
    """G2P: particle state f + 1 from particle state f and grid velocity f."""
    for p in range(n_live(s)):
        g2p_particle(s, f, p)


@ti.kernel
def check_step(s: ti.template(), f: ti.i32):
    for p in range(n_live(s)):
        check_particle(s, f, p, ti.Matrix.zero(float, s.dim, s.dim))
