"""Numerical stability at the edges of the method (thesis 5.3 eq 9, 6.1 eq 14-21, 6.2-6.5 eq 41-71).

Every case either runs, with a finite forward pass and a hand-written gradient dL/dF_pc (Simulator.backward)
that agrees with ti.ad.Tape over the same forward kernels and with central differences, or is refused up front
with a message naming the setting or the particle.

Tolerances (float64), symmetric relative error |a - b| / max(|a|, |b|, tiny):
- manual vs Tape <= 1e-8 (both exact up to round-off);
- manual vs central differences (L(c + eps d) - L(c - eps d)) / 2 eps along random unit directions over all
  controls and along the gradient of one particle's control: <= 1e-5. eps = 1e-5: over 120 steps the round-off
  of L (~1e-16 |L| / eps) reaches 1e-5 of a random directional derivative at eps = 1e-6, while truncation
  (~eps^2) stays below 1e-8 at eps = 1e-5 (measured on the inverted-control case).
  Where the loss is not differentiable, at a symmetric zero-trace F + F_pc (the polar angle atan2(0, 0) of
  eq 9's rotation is undefined, mls_mpm.material.ROTATION_EPS), differences across the point mean nothing:
  there the gradient must be finite and agree with the Tape, and differences are taken only along directions
  that stay on that set, where R = I and the loss is smooth.

Tape(validation=True) checks Taichi's global data access rule only under ti.init(debug=True). This session
runs without debug (re-initialising would free every other module's fields), so the validated Tape runs in
the float32 subprocess, which initialises Taichi in debug mode (test_float32_*).

Scenes: the conftest scene (32 x 32 grid, ~290 particles in a disk, E = 100, nu = 0.2, gamma = 2, gravity,
slip walls) run for 120 steps with stride 10 (12 controls, so control k acts over a horizon of 120 - 10 k
steps), plus one simulator per material extreme (30 steps). Kernels compile once per simulator (about 10 s,
30 s more for the Tape's; Taichi's offline cache shortens repeated runs), so the cases share simulators.
Run with -s to see the gradient-growth and float32 tables.
"""
import json
import math
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from adjoint.material import stress_reverse
from conftest import SCENE, blob, grid_velocity, random_controls, random_unit, rel_err, scene_config
from mls_mpm import ConfigError, MassLoss, PositionLoss, SimConfig, SimulationError, Simulator
from mls_mpm.config import CFLWarning
from mls_mpm.images import splat_grid
from mls_mpm.material import ROTATION_EPS, stress
from mls_mpm.optimize import _clip, gd
from mls_mpm.scene import OptimizeSettings

TAPE_TOL = 1e-8
FD_TOL = 1e-5
EPS = 1e-5
ROOT = Path(__file__).resolve().parent.parent

BASE_STEPS, BASE_STRIDE = 120, 10


# ------------------------------------------------------------------ independent references (numpy)
def polar_rotation_np(F):
    """The rotation closest to F (maximises tr(R^T F)), from the SVD with the sign fixed to det R = +1."""
    U, _, Vt = np.linalg.svd(F)
    if np.linalg.det(U @ Vt) < 0:
        U[:, -1] *= -1.0
    return U @ Vt


def stress_np(F, mu, lam):
    """Eq 9: P = 2 mu (F - R) + lam (J - 1) J F^-T, with J F^-T written as the cofactor matrix."""
    J = np.linalg.det(F)
    cof = np.array([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])
    return 2.0 * mu * (F - polar_rotation_np(F)) + lam * (J - 1.0) * cof


def lame(E, nu):
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def fd(sim, c, d, eps=EPS):
    """Central difference of the loss along d."""
    return (sim.forward(c + eps * d) - sim.forward(c - eps * d)) / (2.0 * eps)


def local_direction(c, k, p, D):
    """A unit direction that moves only control k of particle p, by D."""
    d = np.zeros_like(c)
    d[k, p] = D
    return d / np.linalg.norm(d)


def check_gradient(sim, c, local=(), n_random=2, seed=0, along_gradient=False, tape=True, eps=EPS,
                   tape_tol=TAPE_TOL):
    """Forward finite; manual dL/dF_pc vs the Tape (<= tape_tol, 1e-8 unless given) and vs central differences
    (step eps, <= 1e-5) along n_random random unit directions, along the whole gradient if along_gradient, and,
    for each (k, p) in `local`, along that particle's own gradient. Returns the gradient and the errors."""
    L = sim.forward(c)
    assert np.isfinite(L)
    g = sim.backward()
    assert np.all(np.isfinite(g))
    errors = {}
    if tape:
        errors["tape"] = rel_err(g, sim.gradient_tape(c))
        assert errors["tape"] <= tape_tol
    directions = {f"random {q}": random_unit(c.shape, seed=seed + q) for q in range(n_random)}
    if along_gradient:
        directions["gradient"] = g / np.linalg.norm(g)
    for k, p in local:
        assert np.linalg.norm(g[k, p]) > 0.0
        directions[f"control {k} particle {p}"] = local_direction(c, k, p, g[k, p])
    for name, d in directions.items():
        errors[name] = rel_err(np.sum(g * d), fd(sim, c, d, eps))
        assert errors[name] <= FD_TOL, name
    return g, errors


# ------------------------------------------------------------------ the base scene, 120 steps
class Base:
    """One simulator shared by the control, wall, near-empty-node, NaN and horizon cases."""

    def __init__(self):
        self.cfg = scene_config(steps=BASE_STEPS, stride=BASE_STRIDE)
        self.x0 = blob()
        self.N = len(self.x0)
        theta = 0.2
        R = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
        self.target = (self.x0 - 0.5) @ R.T * 1.1 + 0.5 + np.array([0.03, -0.02])
        self.sim = Simulator(self.cfg, self.x0, loss=PositionLoss(self.target))
        self.c = random_controls(self.sim.control_shape, 0.03, seed=5)
        self.K = self.cfg.n_controls
        # a particle deep inside the disk, and the last control (step 110): singular controls act 10 steps
        self.p = int(np.argmin(np.linalg.norm(self.x0 - np.array([0.52, 0.48]), axis=1)))
        self.k = self.K - 1

    def reset(self, x=None, **kw):
        self.sim.set_initial(self.x0 if x is None else x, **kw)


@pytest.fixture(scope="module")
def base():
    b = Base()
    yield b
    b.reset()


# ------------------------------------------------------------------ CFL limit, drag, Poisson ratio (no kernels)
@pytest.mark.parametrize("E, nu, density, n_grid", [(100.0, 0.2, 1.0, 32), (1e5, 0.3, 2.0, 64), (22.0, 0.49, 40.0, 64),
                                                    (1e-2, 0.0, 1.0, 32)])
def test_cfl_limit_is_dx_over_dilatational_wave_speed(E, nu, density, n_grid):
    """cfl_dt = dx / sqrt((lam + 2 mu) / rho), with the Lame parameters recomputed here from E and nu."""
    cfg = SimConfig(n_grid=n_grid, E=E, nu=nu, density=density, dt=1e-9)
    mu, lam = lame(E, nu)
    assert rel_err(cfg.mu, mu) <= 1e-14 and rel_err(cfg.lam, lam) <= 1e-14
    assert rel_err(cfg.cfl_dt, (1.0 / n_grid) / math.sqrt((lam + 2.0 * mu) / density)) <= 1e-14


def test_dt_at_the_cfl_limit_is_accepted_and_beyond_it_warns():
    """dt = cfl_dt: no warning. dt = 1.01 cfl_dt: CFLWarning quoting the limit dx / wave speed (4 digits)."""
    stiff = dict(n_grid=32, E=1e5, nu=0.3, density=1.0)
    limit = (1.0 / 32) / math.sqrt((lame(1e5, 0.3)[1] + 2.0 * lame(1e5, 0.3)[0]) / 1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CFLWarning)
        SimConfig(dt=limit * (1.0 - 1e-12), **stiff)
    with pytest.warns(CFLWarning, match="CFL limit") as record:
        SimConfig(dt=1.01 * limit, **stiff)
    quoted = float(str(record[0].message).split("= ")[-1].split(";")[0])
    assert rel_err(quoted, limit) <= 5e-4


def test_scene_file_refuses_dt_beyond_the_cfl_limit(tmp_path):
    """A scene whose dt exceeds the CFL limit is refused when loaded, naming sim.dt and the limit."""
    from PIL import Image

    from mls_mpm.scene import SceneError, load_scene
    img = np.full((16, 16, 4), 255, np.uint8)
    img[4:12, 4:12, :3] = 0
    Image.fromarray(img).save(tmp_path / "square.png")
    limit = SimConfig(n_grid=32, E=1e4, nu=0.3, dt=1e-9).cfl_dt
    text = ('[scene]\ninitial = "square.png"\n[sim]\nn_grid = 32\nsteps = 10\nE = 10000.0\nnu = 0.3\n'
            'dt = {dt}\n[control]\nstride = 10\n[loss]\nkind = "position"\n')
    (tmp_path / "ok.toml").write_text(text.format(dt=0.99 * limit))
    assert load_scene(tmp_path / "ok.toml").sim.dt == 0.99 * limit
    (tmp_path / "bad.toml").write_text(text.format(dt=1.01 * limit))
    with pytest.raises(SceneError, match=r"sim\.dt.*CFL limit") as e, warnings.catch_warnings():
        warnings.simplefilter("ignore", CFLWarning)
        load_scene(tmp_path / "bad.toml")
    assert f"{limit:.4g}" in str(e.value)


@pytest.mark.parametrize("gamma_dt", [1.0, 1.0 + 1e-12, 1.5, 1e3])
def test_drag_at_or_above_one_over_dt_is_refused(gamma_dt):
    """gamma dt >= 1 would flip the sign of eq 16's momentum factor (1 - dt gamma): ConfigError naming it."""
    with pytest.raises(ConfigError, match=r"gamma \* dt.*flips sign"):
        SimConfig(dt=1e-3, gamma=gamma_dt / 1e-3)


@pytest.mark.parametrize("gamma", [float("inf"), float("nan"), -1.0])
def test_drag_must_be_finite_and_non_negative(gamma):
    """gamma = inf would pass gamma dt >= 1 only by accident and nan not at all: both refused, as is gamma < 0."""
    with pytest.raises(ConfigError, match="gamma"):
        SimConfig(dt=1e-3, gamma=gamma)


@pytest.mark.parametrize("nu", [0.5, 0.51, -0.1, float("nan")])
def test_poisson_ratio_outside_zero_to_half_is_refused(nu):
    """nu -> 1/2 sends lam = E nu / ((1 + nu)(1 - 2 nu)) to infinity: refused from 0.5 on."""
    with pytest.raises(ConfigError, match="nu"):
        SimConfig(nu=nu)


# ------------------------------------------------------------------ eq 9 and its derivative over nu and J
@ti.kernel
def _stress_kernel(Fs: ti.template(), W: ti.template(), P: ti.template(), loss: ti.template(), mu: ti.f64,
                   lam: ti.f64):
    for q in Fs:
        P[q] = stress(Fs[q], mu, lam)
        loss[None] += (W[q] * stress(Fs[q], mu, lam)).sum()


@ti.kernel
def _stress_reverse_kernel(Fs: ti.template(), W: ti.template(), out: ti.template(), mu: ti.f64, lam: ti.f64):
    for q in Fs:
        out[q] = stress_reverse(Fs[q], W[q], mu, lam)


MATERIAL_F = {
    "near identity": np.array([[1.05, 0.1], [-0.08, 0.97]]),
    "compressed, J = 1e-6": np.array([[0.9, 0.3], [0.6, 0.2 + 1e-6 / 0.9]]),
    "singular, J = 0": np.array([[0.75, 0.5], [0.375, 0.25]]),
    "inverted, J = -0.56": np.array([[0.75, 0.5], [0.375, -0.5]]),
    "near the polar singularity, r = 2e-3": np.array([[0.8 + 1e-3, 0.3], [0.3, -0.8 + 1e-3]]),
}


@pytest.fixture(scope="module")
def stress_fields():
    """Fields for the MATERIAL_F cases, made once so that the two kernels compile once (mu, lam are arguments)."""
    M = len(MATERIAL_F)
    return dict(Fs=ti.Matrix.field(2, 2, ti.f64, shape=M, needs_grad=True), W=ti.Matrix.field(2, 2, ti.f64, shape=M),
                P=ti.Matrix.field(2, 2, ti.f64, shape=M, needs_grad=True), out=ti.Matrix.field(2, 2, ti.f64, shape=M),
                loss=ti.field(ti.f64, shape=(), needs_grad=True))


@pytest.mark.parametrize("nu", [0.0, 0.2, 0.4, 0.45, 0.49])
def test_stress_and_its_derivative_over_poisson_ratio_and_volume(stress_fields, nu):
    """For nu from 0 to 0.49 and F from J = 1 through J = 1e-6, 0 and < 0 to next to the polar singularity:

    - P(F) (mls_mpm.material.stress) equals eq 9 with R from an SVD, rel err <= 1e-12;
    - stress_reverse(F, G) = dP/dF : G equals the Tape through stress, rel err <= 1e-8, and central
      differences of G : P(F + h D) of the SVD-based eq 9 along random D, rel err <= 1e-5 (h = 1e-7 r,
      with r = |(F00 + F11, F10 - F01)| the scale over which R turns).
    E = 1e3 (lam reaches 1.6e4 at nu = 0.49).
    """
    mu, lam = lame(1e3, nu)
    names = list(MATERIAL_F)
    M = len(names)
    F = np.stack([MATERIAL_F[n] for n in names])
    rng = np.random.default_rng(int(nu * 100))
    G = rng.standard_normal((M, 2, 2))
    Fs, W, P, out, loss = (stress_fields[k] for k in ("Fs", "W", "P", "out", "loss"))
    Fs.from_numpy(F)
    W.from_numpy(G)
    with ti.ad.Tape(loss=loss):  # clears Fs.grad and P.grad, zeroes loss
        _stress_kernel(Fs, W, P, loss, mu, lam)
    _stress_reverse_kernel(Fs, W, out, mu, lam)
    P_ti, tape, got = P.to_numpy(), Fs.grad.to_numpy(), out.to_numpy()
    for q, name in enumerate(names):
        assert np.all(np.isfinite(got[q])), name
        assert rel_err(P_ti[q], stress_np(F[q], mu, lam)) <= 1e-12, name
        assert rel_err(got[q], tape[q]) <= TAPE_TOL, name
        r = math.hypot(F[q, 0, 0] + F[q, 1, 1], F[q, 1, 0] - F[q, 0, 1])
        h = 1e-7 * min(r, 1.0)
        for s in range(2):
            D = rng.standard_normal((2, 2))
            diff = (np.sum(G[q] * stress_np(F[q] + h * D, mu, lam))
                    - np.sum(G[q] * stress_np(F[q] - h * D, mu, lam))) / (2 * h)
            assert rel_err(np.sum(got[q] * D), diff) <= FD_TOL, (name, s)


# ------------------------------------------------------------------ long horizons
def test_gradient_growth_with_horizon(base, capsys):
    """dL/dF_pc^k reaches back over 120 - 10 k steps; per horizon: |g_k|, manual vs Tape (<= 1e-8) and vs
    central differences along g_k (<= 1e-5). Prints the table (run with -s)."""
    sim, c = base.sim, base.c
    base.reset()
    sim.forward(c)
    g = sim.backward()
    g_tape = sim.gradient_tape(c)
    rows = []
    for k in range(base.K - 1, -1, -1):
        horizon = BASE_STEPS - k * BASE_STRIDE
        d = np.zeros_like(c)
        d[k] = g[k] / np.linalg.norm(g[k])
        rows.append((horizon, np.linalg.norm(g[k]), rel_err(g[k], g_tape[k]), rel_err(np.sum(g * d), fd(sim, c, d))))
    with capsys.disabled():
        print(f"\ngradient growth, {base.N} particles, dt = {base.cfg.dt:g}, E = {base.cfg.E:g}, "
              f"gamma = {base.cfg.gamma:g}, position loss")
        print(f"{'steps':>6} {'|dL/dF_pc^k|':>14} {'growth':>8} {'vs Tape':>10} {'vs FD':>10}")
        for h, n, et, ef in rows:
            print(f"{h:>6} {n:>14.4e} {n / rows[0][1]:>8.2f} {et:>10.1e} {ef:>10.1e}")
    for h, n, et, ef in rows:
        assert np.isfinite(n) and n > 0.0, h
        assert et <= TAPE_TOL, h
        assert ef <= FD_TOL, h


# ------------------------------------------------------------------ singular controls
def singular_controls(base, M, particles=None):
    """Controls c with F + F_pc = M at step k * stride for the given particles (default: base.p)."""
    particles = [base.p] if particles is None else particles
    c = base.c.copy()
    c[base.k, particles] = 0.0
    base.sim.forward(c)
    F = base.sim.state(base.k * BASE_STRIDE)["F"]  # does not depend on control k
    c[base.k, particles] = M - F[particles]
    return c


SINGULAR = {
    "near singular, J = 1e-6": np.array([[0.9, 0.3], [0.6, 0.2 + 1e-6 / 0.9]]),
    "singular, J = 0": np.array([[0.75, 0.5], [0.375, 0.25]]),
    "inverted, J < 0": np.array([[0.75, 0.5], [0.375, -0.5]]),
    "inverted reflection, J = -0.98": np.diag([1.0, -1.0]) + np.array([[0.0, 0.2], [-0.1, 0.0]]),
}


@pytest.mark.parametrize("name", list(SINGULAR))
def test_singular_control(base, name):
    """F + F_pc = M (J = 1e-6, 0, -0.56, -0.98) for one particle at step 110: the forward stays finite, det F of the
    next step is det(I + dt C) det M (the singular state was reached), and the gradient matches the Tape and
    central differences (F + F_pc is away from the polar singularity, so the loss is smooth there)."""
    base.reset()
    M = SINGULAR[name]
    c = singular_controls(base, M)
    g, _ = check_gradient(base.sim, c, local=[(base.k, base.p)], seed=10)
    sim, f, p = base.sim, base.k * BASE_STRIDE, base.p
    sim.forward(c)
    C1, F1 = sim.state(f + 1)["C"][p], sim.state(f + 1)["F"][p]
    assert abs(np.linalg.det(F1) - np.linalg.det(np.eye(2) + base.cfg.dt * C1) * np.linalg.det(M)) <= 1e-12
    assert np.all(np.isfinite(sim.state(BASE_STEPS)["F"]))


POLAR = np.array([[0.8, 0.3], [0.3, -0.8]])  # symmetric, zero trace: atan2(0, 0), and J = -0.73


def in_set_direction(g):
    """The part of a 2x2 gradient along symmetric zero-trace matrices [[a, b], [b, -a]] (the singular set)."""
    a, b = (g[0, 0] - g[1, 1]) / 2.0, (g[0, 1] + g[1, 0]) / 2.0
    return np.array([[a, b], [b, -a]])


def test_polar_singular_control(base):
    """F + F_pc symmetric with zero trace for one particle at step 110: eq 9's rotation angle atan2(0, 0) is
    undefined; polar_rotation takes R = I and stress_reverse drops the rotation term (ROTATION_EPS guard).

    The loss jumps across this point (R turns by up to pi), so differences across it mean nothing. Checked:
    the state reached the set (r^2 = (F00 + F11)^2 + (F10 - F01)^2 <= ROTATION_EPS, computed as the kernel
    does); the forward and the gradient are finite; manual == Tape (<= 1e-8); and along symmetric zero-trace
    directions, where R stays I and the loss is smooth, manual == central differences (<= 1e-5).
    """
    base.reset()
    sim, k, p = base.sim, base.k, base.p
    c = singular_controls(base, POLAR)
    sim.forward(c)
    Fs = sim.state(k * BASE_STRIDE)["F"][p] + c[k, p]
    assert (Fs[0, 0] + Fs[1, 1]) ** 2 + (Fs[1, 0] - Fs[0, 1]) ** 2 <= ROTATION_EPS
    g, _ = check_gradient(sim, c, n_random=0)
    for d in (local_direction(c, k, p, in_set_direction(g[k, p])),
              local_direction(c, k, p, in_set_direction(np.random.default_rng(3).standard_normal((2, 2))))):
        assert rel_err(np.sum(g * d), fd(sim, c, d)) <= FD_TOL


def test_near_polar_singular_gradient_grows_like_one_over_r(base, capsys):
    """F + F_pc = POLAR + delta I, r = 2 delta from the singular set: the rotation's derivative
    dtheta = (a db - b da) / r^2 makes |dL/dF_pc| grow like 1 / r, finite down to the guard r^2 = ROTATION_EPS.

    Per delta: finite; manual == Tape (<= 1e-8 + 8 eps / r, eps the float64 epsilon: the parallel schedule sums
    each node's mass and momentum in another order than the Tape's forward, lane by lane, and the 1 / r derivative
    amplifies that round-off; measured 1.8e-12, 1.9e-10, 1.9e-8 at r = 2e-4, 2e-6, 2e-8, serial ~1e-13); central
    differences with eps = 1e-3 r (smooth on that scale)
    along the particle's gradient (<= 1e-5); and |g| r constant to 5 % once the rotation term dominates.
    """
    base.reset()
    sim, k, p = base.sim, base.k, base.p
    rows = []
    for delta in (1e-4, 1e-6, 1e-8):
        c = singular_controls(base, POLAR + delta * np.eye(2))
        g, _ = check_gradient(sim, c, n_random=0, tape_tol=TAPE_TOL + 8.0 * np.finfo(np.float64).eps / (2 * delta))
        d = local_direction(c, k, p, g[k, p])
        err = rel_err(np.sum(g * d), fd(sim, c, d, eps=1e-3 * 2 * delta))
        assert err <= FD_TOL, delta
        rows.append((2 * delta, np.linalg.norm(g[k, p]), err))
    with capsys.disabled():
        print("\nnear the polar singularity: r, |dL/dF_pc| of the particle, rel err vs FD (eps = 1e-3 r)")
        for r, n, err in rows:
            print(f"  r = {r:.0e}  |g| = {n:.4e}  |g| r = {n * r:.4e}  fd {err:.1e}")
    products = [n * r for r, n, _ in rows]
    assert max(products) / min(products) <= 1.05


def test_all_particles_collapsed_to_zero(base):
    """F + F_pc = 0 for every particle at step 110 (J = 0 and r = 0 at once). The stress term P F^T of eq 16
    vanishes, so F stays exactly 0 (eq 20) and the forward is finite; the gradient is finite and equals the Tape.

    No differences: at F = 0 the derivative of P(F) F^T is -2 mu R dF^T with the undefined R, so the loss has
    no derivative there in any direction (observed: central differences off by ~100 %)."""
    base.reset()
    c = singular_controls(base, np.zeros((2, 2)), particles=list(range(base.N)))
    check_gradient(base.sim, c, n_random=0)
    base.sim.forward(c)
    assert np.all(base.sim.state(BASE_STEPS)["F"] == 0.0)
    assert np.all(np.isfinite(base.sim.state(BASE_STEPS)["x"]))


# ------------------------------------------------------------------ walls and near-empty grid nodes
def wall_positions(N, n_grid):
    """N particles, 4 per cell, in two slabs: one in the bottom-left corner with its first row and column on
    x = dx and y = dx, one in the top-right corner up to just below 1 - 2 dx: the extreme positions where a
    particle's 4x4 stencil still fits on the grid (Simulator.set_initial), inside the walls' zone."""
    dx = 1.0 / n_grid
    lo, hi = dx, 1.0 - 2.0 * dx
    h = dx / 2.0
    side = int(math.ceil(math.sqrt(N / 2.0)))
    i, j = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    ij = np.stack([i.ravel(), j.ravel()], axis=1) * h
    low = lo + ij
    high = hi - 1e-9 * dx - ij
    return np.concatenate([low, high])[:N]


def test_particles_touching_the_walls(base):
    """Particles on the lowest and highest admissible positions, in the slip walls' zone (bound = 3 cells):
    they stay on the grid, the forward is finite and the gradient matches the Tape and central differences."""
    x = wall_positions(base.N, base.cfg.n_grid)
    dx = base.cfg.dx
    assert x.min() == dx and x.max() < 1.0 - 2.0 * dx and x.max() > 1.0 - 2.0 * dx - 1e-6
    base.reset(x)
    try:
        c = random_controls(base.sim.control_shape, 0.03, seed=7)
        check_gradient(base.sim, c, local=[(0, 0), (0, base.N - 1)], seed=20)
        xs = base.sim.state(BASE_STEPS)["x"]
        assert xs.min() >= dx and xs.max() < 1.0 - 2.0 * dx
    finally:
        base.reset()


# pairs of particles, half a cell apart, away from the body: their stencils' outer nodes barely reach a node
# (position / dx, the fraction 0.995 / 0.005 puts the cubic B-spline's tail (2 - 1.995)^3 / 6 ~ 2e-8 there)
LONERS = {0: (6.995, 24.5), 1: (6.995, 25.0), 2: (24.005, 8.5), 3: (24.005, 9.0),
          4: (7.5, 6.996), 5: (8.0, 6.996), 6: (24.5, 24.997), 7: (25.0, 24.997)}


def bspline_np(t):
    """Cubic B-spline N1(t) (eq 1-2)."""
    a = np.abs(t)
    return np.where(a < 1.0, 0.5 * a ** 3 - a ** 2 + 2.0 / 3.0, np.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0))


def loner_setup(base):
    """Step 0 with the LONERS moved into place; returns the base controls, their gradient and the unit direction
    of that gradient restricted to the loners' controls."""
    x = base.x0.copy()
    for p, (i, j) in LONERS.items():
        x[p] = (i * base.cfg.dx, j * base.cfg.dx)
    base.reset(x)
    c = base.c.copy()
    base.sim.forward(c)
    g = base.sim.backward()
    d = np.zeros_like(c)
    d[:, list(LONERS)] = g[:, list(LONERS)]
    return c, g, d / np.linalg.norm(d)


def test_nodes_with_near_zero_mass(base):
    """Pairs of isolated particles placed so that nodes of their stencils get N m_p with N ~ 1e-9..1e-8, just
    (the old empty-node cut was at 1e-10 m_p; now only m_eps = 1e-20 m_p guards the division): eq 17
    (v_i = p_i / m_i) and eq 52-53 (1 / m_i, 1 / m_i^2) divide by these masses. (A lone particle would not do: the B-spline reproduces linear functions, so its own
    stress never moves it and dL/dF_pc would be zero.)

    Checked at step 0: such nodes exist (1e-10 m_p < m_i < 1e-7 m_p) and their velocity equals
    sum_p N_ip G_p (x_i - x_p) / (m_p sum_p N_ip) + dt g, G_p = -3/dx^2 dt V_p P (F + F_pc)^T (eq 16-17, v = 0,
    C = 0 at step 0), to 1e-9, with P from the SVD-based eq 9 and the weights recomputed here; the gradient is
    finite and matches the Tape and central differences along it. (Differences along the loners' own controls:
    test_loss_is_continuous_where_nodes_empty.)"""
    cfg = base.cfg
    dx = cfg.dx
    try:
        c, _, _ = loner_setup(base)
        sim = base.sim
        x = sim.state(0)["x"]
        sim.forward(c)
        m, v = sim.fields.grid_mass()[0], grid_velocity(sim, 0)
        mu, lam = lame(cfg.E, cfg.nu)
        light = 0
        for p in LONERS:
            stencil = np.stack(np.meshgrid(range(4), range(4)), -1).reshape(-1, 2)
            for node in np.floor(x[p] / dx).astype(int) - 1 + stencil:
                if not 1e-10 * cfg.m_p < m[tuple(node)] < 1e-7 * cfg.m_p:
                    continue
                light += 1
                num, den = np.zeros(2), 0.0
                for q in LONERS:
                    N = np.prod(bspline_np(node - x[q] / dx))
                    Fs = np.eye(2) + c[0, q]
                    G = -3.0 / dx ** 2 * cfg.dt * cfg.vol * stress_np(Fs, mu, lam) @ Fs.T
                    num += N * G @ (node * dx - x[q])
                    den += N * cfg.m_p
                assert rel_err(m[tuple(node)], den) <= 1e-9, (p, node)
                assert rel_err(v[tuple(node)], num / den + cfg.dt * np.array(cfg.gravity)) <= 1e-9, (p, node)
        assert light >= 8
        check_gradient(sim, c, n_random=0, along_gradient=True)
    finally:
        base.reset()


def test_loss_is_continuous_where_nodes_empty(base, capsys):
    """Along the pairs' joint gradient direction d: L(c + t d) for 101 t in [-1e-3, 1e-3] deviates from its
    least-squares cubic by round-off only (<= 2e-14, measured 6e-15; the old cut of nodes below 1e-10 m_p made L
    jump by ~1e-12, and a kinked floor max(m_i, 1e-10 m_p) left 7e-14), and central differences with eps = 1e-5,
    3e-5 and 1e-4 match <g, d> to 1e-5.

    Every term of p_i (eq 16) and of dL/dv_i (eq 48) carries the weight N_ip that m_i (eq 15) carries, so
    p_i / m_i and the quotients of eq 50-53 stay bounded as m_i -> 0, and G2P multiplies them by N_ip again:
    with the smooth guard m_i + m_eps (mls_mpm/grid.py free_velocity) rather than a cut, a node entering or
    leaving a particle's support changes nothing discontinuously."""
    try:
        c, g, d = loner_setup(base)
        sim = base.sim
        t = np.linspace(-1e-3, 1e-3, 101)
        L = np.array([sim.forward(c + t_ * d) for t_ in t])
        residual = np.abs(L - np.polyval(np.polyfit(t, L, 3), t)).max()
        errors = {eps: rel_err(np.sum(g * d), fd(sim, c, d, eps)) for eps in (1e-5, 3e-5, 1e-4)}
        with capsys.disabled():
            print(f"\nnear-empty nodes: |L - cubic fit| <= {residual:.1e}; fd errors "
                  + ", ".join(f"eps {e:.0e}: {v:.1e}" for e, v in errors.items()))
        assert residual <= 2e-14
        assert max(errors.values()) <= FD_TOL
    finally:
        base.reset()


def test_particle_leaving_the_grid_is_named(base):
    """An isolated particle thrown at the left wall at 10 cells per step leaves the grid in one step: SimulationError
    naming step 1 and that particle, raised by forward() before any loss is returned."""
    dx = base.cfg.dx
    p = 7
    x = base.x0.copy()
    x[p] = (5.5 * dx, 0.2)
    v = np.zeros_like(x)
    v[p] = (-10.0 * dx / base.cfg.dt, 0.0)
    base.reset(x, v=v)
    try:
        with pytest.raises(SimulationError, match=rf"^step 1: particle {p} left the simulation grid"):
            base.sim.forward(base.c)
    finally:
        base.reset()


# ------------------------------------------------------------------ NaN and Inf
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("name", ["x", "v", "C", "F"])
def test_non_finite_initial_state_is_refused(base, name, bad):
    """A NaN or Inf in one particle's x, v, C or F (set_initial) is refused before anything is written:
    ValueError naming the array and the particle; the stored step 0 is unchanged."""
    base.reset()
    before = base.sim.state(0)
    N, p = base.N, 123
    arrays = {"x": base.x0.copy(), "v": np.zeros((N, 2)), "C": np.zeros((N, 2, 2)), "F": np.tile(np.eye(2), (N, 1, 1))}
    arrays[name][p].flat[-1] = bad
    with pytest.raises(ValueError, match=rf"^{name}: particle {p} holds NaN or Inf"):
        base.sim.set_initial(arrays["x"], v=arrays["v"], C=arrays["C"], F=arrays["F"])
    after = base.sim.state(0)
    assert all(np.array_equal(before[k], after[k]) for k in before)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_control_is_refused(base, bad):
    """A NaN or Inf in one control entry: ValueError naming the control, its step and the particle, from
    forward() and from gradient_tape()."""
    base.reset()
    c = base.c.copy()
    c[3, 45, 1, 0] = bad
    msg = r"^controls: control 3 \(step 30\), particle 45 holds NaN or Inf"
    with pytest.raises(ValueError, match=msg):
        base.sim.forward(c)
    with pytest.raises(ValueError, match=msg):
        base.sim.gradient_tape(c)


def test_non_finite_state_inside_the_simulation_is_named(base):
    """The kernels' own check (check_particle), behind set_initial's: a NaN written straight into step 0's F of
    particle p (mls_mpm.state.write_step, bypassing set_initial) must be reported by forward() as a non-finite
    state of that particle at step 0, before P2G spreads it to the grid."""
    from mls_mpm.state import write_step
    base.reset()
    p = base.p
    F = np.tile(np.eye(2), (base.N, 1, 1))
    F[p, 0, 1] = np.nan
    write_step(base.sim.fields, 0, base.x0, np.zeros((base.N, 2)), np.zeros((base.N, 2, 2)), F)
    try:
        with pytest.raises(SimulationError) as e:
            base.sim.forward(base.c)
        assert str(e.value).startswith(f"step 0: particle {p} has a non-finite state"), str(e.value)
    finally:
        base.reset()


def test_overflowing_control_is_named_at_its_source(base):
    """A finite but huge control (1e200 I on particle p at step 110) overflows eq 9 (J ~ 1e400 = Inf) in P2G:
    the SimulationError must name that step and that particle (not a neighbour infected one step later)."""
    base.reset()
    c = base.c.copy()
    p = base.p
    c[base.k, p] = 1e200 * np.eye(2)
    with pytest.raises(SimulationError) as e:
        base.sim.forward(c)
    assert str(e.value).startswith(f"step {base.k * BASE_STRIDE}: particle {p} "), str(e.value)
    # the hint follows the evidence: dt is below the CFL limit and gravity is mild, the control is the cause
    assert "likely cause: controls up to |F_pc| = 1.41e+200" in str(e.value) and "CFL" not in str(e.value)


def test_non_finite_adjoint_is_named(base):
    """backward() never returns NaN: a NaN in a stored state that only the reverse pass reads (C of the last
    step, written straight into the fields after forward(); eq 20's (I + dt C^{n+1})^T dL/dF^{n+1}) must raise
    SimulationError naming the reverse step and the particle."""
    from mls_mpm.state import write_step
    base.reset()
    sim, p, T = base.sim, base.p, BASE_STEPS
    sim.forward(base.c)
    end = sim.state(T)
    C = end["C"].copy()
    C[p, 0, 0] = np.nan
    write_step(sim.fields, T, end["x"], end["v"], C, end["F"])
    try:
        with pytest.raises(SimulationError, match=rf"^backward, step {T - 1}: particle {p} has a non-finite adjoint"):
            sim.backward()
    finally:
        sim.forward(base.c)


# ------------------------------------------------------------------ repeated passes, gradient clipping
def test_repeated_passes_do_not_accumulate(base):
    """backward() and gradient_tape() twice give the same gradient bit for bit (their accumulators, adj_F_pc
    and the Tape's .grad fields, are cleared each time), also after a pass with other controls in between."""
    base.reset()
    sim, c = base.sim, base.c
    sim.forward(c)
    g1 = sim.backward()
    g2 = sim.backward()
    t1 = sim.gradient_tape(c)
    sim.forward(2.0 * c)
    sim.backward()
    sim.gradient_tape(2.0 * c)
    sim.forward(c)
    g3 = sim.backward()
    t2 = sim.gradient_tape(c)
    assert np.array_equal(g1, g2) and np.array_equal(g1, g3) and np.array_equal(t1, t2)
    assert rel_err(g1, t1) <= TAPE_TOL


def test_gradient_clipping(base):
    """optimize._clip(g, clip): a gradient longer than clip is scaled to norm clip along the same direction
    (cosine 1 to 1e-15), a shorter one and clip = 0 leave it unchanged, a zero gradient stays zero (no 0/0);
    the clipped manual gradient of the 120-step scene is still a descent direction (central differences
    along it equal -|g| clip to 1e-5)."""
    base.reset()
    sim, c = base.sim, base.c
    sim.forward(c)
    g = sim.backward()
    n = np.linalg.norm(g)
    for clip in (0.5 * n, 1e-3 * n):
        gc = _clip(g, clip)
        assert rel_err(np.linalg.norm(gc), clip) <= 1e-14
        assert abs(np.sum(gc * g) / (np.linalg.norm(gc) * n) - 1.0) <= 1e-15
        assert rel_err(-np.sum(g * gc) / clip, fd(sim, c, -gc / clip)) <= FD_TOL
    assert np.array_equal(_clip(g, 2.0 * n), g) and np.array_equal(_clip(g, 0.0), g)
    zero = np.zeros_like(g)
    assert np.array_equal(_clip(zero, 1.0), zero)


def test_gradient_descent_with_clipping(base):
    """gd (Algorithm 1) with settings.clip = 1e-3, below every control's gradient norm (>= 5e-3 here): every
    gradient it steps along has norm exactly clip, and the loss decreases."""
    base.reset()
    sim, c = base.sim, base.c
    L0 = sim.forward(c)
    clip = 1e-3
    assert min(np.linalg.norm(gk) for gk in sim.backward()) > 5.0 * clip
    settings = OptimizeSettings(method="gd", iterations=1, step="raw", lr=1.0, line_search=4, tol=0.0, clip=clip)
    result = gd(sim, c, settings, emit=lambda *a: None)
    assert len(result.grad_norms) == base.K
    assert max(rel_err(n, clip) for n in result.grad_norms) <= 1e-12
    assert result.losses[-1] < L0
    assert rel_err(sim.forward(result.controls), result.losses[-1]) <= 1e-12


# ------------------------------------------------------------------ material extremes, 30 steps each
def material_case(name):
    """(config, finite-difference step) of one extreme; dt at the CFL limit is computed here from the wave speed.

    The very soft material's gradient is ~1e-5 (controls act through a stress 1e4 times weaker), so its
    directional derivatives (~1e-7) need eps = 1e-3 to rise above the round-off of L; its loss is nearly
    linear in the controls there (truncation ~3e-7)."""
    if name == "stiff, nu = 0.49, dt = CFL limit":
        mu, lam = lame(1e3, 0.49)
        return SimConfig(**{**SCENE, "E": 1e3, "nu": 0.49, "dt": (1.0 / 32) / math.sqrt(lam + 2.0 * mu)}), EPS
    if name == "very soft, nu = 0":
        return scene_config(E=1e-2, nu=0.0), 1e-3
    if name == "drag, gamma dt = 0.95":
        return scene_config(gamma=950.0), EPS
    raise ValueError(name)


MATERIALS = ["stiff, nu = 0.49, dt = CFL limit", "very soft, nu = 0", "drag, gamma dt = 0.95"]


class Materials(dict):
    """One simulator per material extreme, built on first use (each compiles its own kernels)."""

    def __missing__(self, name):
        cfg, _ = material_case(name)
        x0 = blob()
        sim = Simulator(cfg, x0, loss=PositionLoss(x0 * 1.1 - 0.05 + np.array([0.02, -0.01])))
        self[name] = (sim, x0)
        return self[name]


@pytest.fixture(scope="module")
def materials():
    return Materials()


@pytest.mark.slow
@pytest.mark.parametrize("name", MATERIALS)
def test_material_extreme(materials, name):
    """30 steps at a material extreme, random controls of size 0.05: forward finite, gradient == Tape (<= 1e-8)
    and == central differences (<= 1e-5) along random directions and along one particle's control.

    - stiff, nearly incompressible: E = 1e3, nu = 0.49 (lam = 1.6e4), dt exactly dx / sqrt((lam + 2 mu) / rho)
      (no CFLWarning at the limit); the state stays bounded (|F - I| < 0.5, |v| < 5);
    - very soft: E = 1e-2, nu = 0 (lam = 0);
    - heavy drag: gamma dt = 0.95, so eq 16 keeps 5 % of the momentum; checked on a uniform initial velocity
      without controls: one step gives v = (1 - dt gamma) v0 + dt g for every particle (to 1e-9).
    """
    with warnings.catch_warnings():
        warnings.simplefilter("error", CFLWarning)
        sim, x0 = materials[name]
    c = random_controls(sim.control_shape, 0.05, seed=11)
    sim.set_initial(x0)
    check_gradient(sim, c, local=[(0, len(x0) // 2)], seed=40, eps=material_case(name)[1])
    end = sim.state(sim.cfg.steps)
    assert np.all(np.isfinite(end["x"])) and np.all(np.isfinite(end["F"]))
    if name.startswith("stiff"):
        assert rel_err(sim.cfg.dt, sim.cfg.cfl_dt) <= 1e-15
        assert np.abs(end["F"] - np.eye(2)).max() < 0.5 and np.abs(end["v"]).max() < 5.0
    if name.startswith("drag"):
        v0 = np.tile([0.3, -0.2], (len(x0), 1))
        try:
            sim.set_initial(x0, v=v0)
            sim.forward(np.zeros(sim.control_shape))
            cfg = sim.cfg
            expected = (1.0 - cfg.dt * cfg.gamma) * v0[0] + cfg.dt * np.array(cfg.gravity)
            assert rel_err(sim.state(1)["v"], np.tile(expected, (len(x0), 1))) <= 1e-9
        finally:
            sim.set_initial(x0)


# ------------------------------------------------------------------ zero target mass
class ZeroTargets(dict):
    """Simulators with all-zero targets: mass on a 32 and a 16 grid (weights 1, 0.5), or log mass on 32."""

    def __missing__(self, log):
        cfg = scene_config(steps=20)
        x0 = blob()
        targets = [np.zeros((32, 32)), np.zeros((16, 16))]
        loss = MassLoss(targets[:1] if log else targets, weights=None if log else [1.0, 0.5], log=log)
        self[log] = (Simulator(cfg, x0, loss=loss), x0)
        return self[log]


@pytest.fixture(scope="module")
def zero_targets():
    return ZeroTargets()


def zero_loss_np(cfg, log, x):
    """The zero-target losses from positions x, with the node masses splatted in numpy (images.splat_grid):
    mass (eq 11 on a 32 and a 16 grid, weights 1 and 0.5) sum_g w_g / 2 sum_i m_i^2, log mass
    1/2 sum_i ln(m_i + 1)^2 on the 32 grid."""
    if log:
        return 0.5 * np.sum(np.log1p(splat_grid(x, cfg.m_p, 32)) ** 2)
    return sum(w * 0.5 * np.sum(splat_grid(x, cfg.m_p, res) ** 2) for w, res in ((1.0, 32), (0.5, 16)))


@pytest.mark.parametrize("log", [False, True], ids=["mass", "log mass"])
def test_zero_target_mass_loss_and_seed(zero_targets, log):
    """All-zero target grids (an empty target) at the loss: the loss of a deformed disk (evaluate_positions,
    no physics) equals zero_loss_np to 1e-12 and its dL/dx_p (eq 41-43; log mass: seed ln(m_i + 1) / (m_i + 1))
    is finite and equals central differences of zero_loss_np (h = 1e-7) to 1e-6."""
    sim, x0 = zero_targets[log]
    x = x0 + 0.2 * sim.cfg.dx * np.random.default_rng(13).standard_normal(x0.shape)
    L, gx = sim.evaluate_positions(x)
    assert L > 0.0 and rel_err(L, zero_loss_np(sim.cfg, log, x)) <= 1e-12
    assert np.all(np.isfinite(gx))
    h = 1e-7
    for q in range(2):
        d = random_unit(x.shape, seed=50 + q)
        diff = (zero_loss_np(sim.cfg, log, x + h * d) - zero_loss_np(sim.cfg, log, x - h * d)) / (2 * h)
        assert rel_err(np.sum(gx * d), diff) <= 1e-6


@pytest.mark.slow
def test_zero_target_log_mass_gradient(zero_targets):
    """A 20-step trajectory against an all-zero log-mass target (its seed divides by m_i + 1): the loss equals
    zero_loss_np of the final positions (1e-12), and the gradient is finite and matches the Tape (<= 1e-8) and
    central differences (<= 1e-5). (The plain mass seed divides by nothing; the seed-level test above covers
    it, and test_gradients its trajectory with non-zero targets: a simulator costs ~40 s to compile cold.)"""
    sim, _ = zero_targets[True]
    c = random_controls(sim.control_shape, 0.05, seed=12)
    L = sim.forward(c)
    assert rel_err(L, zero_loss_np(sim.cfg, True, sim.state(sim.cfg.steps)["x"])) <= 1e-12
    check_gradient(sim, c, seed=60, along_gradient=True)


MASS_SCENE = ('[scene]\ninitial = "initial.png"\ntarget = "target.png"\n[sim]\nn_grid = 32\nsteps = 10\n'
              'dt = 1e-3\nE = 100.0\n[control]\nstride = 10\n[loss]\nkind = "mass"\n')


def _png(path, rgba):
    from PIL import Image
    Image.fromarray(np.asarray(rgba, np.uint8)).save(path)


@pytest.mark.parametrize("kind", ["transparent", "white"])
def test_empty_target_image_is_refused(tmp_path, kind):
    """A target image without material (all transparent, or all white) would give an all-zero target: the
    scene is refused when built, naming scene.target and what is expected, before any simulation."""
    from mls_mpm.problem import build
    from mls_mpm.scene import SceneError, load_scene
    square = np.zeros((16, 16, 4), np.uint8)
    square[..., 3] = 255
    square[4:12, 4:12, :3] = 0
    square[:4, :, :3] = square[12:, :, :3] = square[:, :4, :3] = square[:, 12:, :3] = 255
    _png(tmp_path / "initial.png", square)
    empty = np.zeros((16, 16, 4)) if kind == "transparent" else np.full((16, 16, 4), 255)
    _png(tmp_path / "target.png", empty)
    (tmp_path / "s.toml").write_text(MASS_SCENE)
    scene = load_scene(tmp_path / "s.toml")
    with pytest.raises(SceneError, match=r"scene\.target = .*target\.png.*expected an image with material"):
        build(scene)


def test_all_black_target_and_empty_grids_in_the_metrics(tmp_path):
    """An all-black target image is all material (black is not background): the target grid covers the region
    and holds the initial body's total mass (target_density "match"). The summary metrics take empty grids
    without dividing by zero: iou of two empty grids is 1, mass_outside of an empty mass grid is 0."""
    from mls_mpm.problem import build, iou, mass_outside, occupied
    from mls_mpm.scene import load_scene
    square = np.full((16, 16, 4), 255, np.uint8)
    square[4:12, 4:12, :3] = 0
    _png(tmp_path / "initial.png", square)
    _png(tmp_path / "target.png", np.concatenate([np.zeros((16, 16, 3)), np.full((16, 16, 1), 255)], axis=-1))
    (tmp_path / "s.toml").write_text(MASS_SCENE)
    scene = load_scene(tmp_path / "s.toml")
    problem = build(scene)
    target = problem.target_mass_grids[0]
    assert np.all(np.isfinite(target))
    assert rel_err(target.sum(), len(problem.x0) * scene.sim.m_p) <= 1e-12
    assert len(problem.target_points) >= 3.9 * len(problem.x0)  # the whole image vs its middle quarter
    zero = np.zeros((32, 32))
    assert iou(occupied(zero, 1.0), occupied(zero, 1.0)) == 1.0
    assert mass_outside(zero, target) == 0.0 and mass_outside(zero, zero) == 0.0
    assert mass_outside(target, zero) == 1.0


# ------------------------------------------------------------------ float32 against float64 (subprocess)
FLOAT32_SCRIPT = r'''
import json, sys
import numpy as np
import taichi as ti
# float32, and debug mode: bounds-checked kernels and Tape(validation=True) (Taichi checks it only in debug)
ti.init(arch=ti.cpu, default_fp=ti.f32, fast_math=False, debug=True, log_level=ti.ERROR)
import mls_mpm
from conftest import SCENE
data = np.load(sys.argv[1])
cfg = mls_mpm.SimConfig(**{**SCENE, "steps": int(data["steps"]), "stride": int(data["stride"]), "dtype": "f32"})
sim = mls_mpm.Simulator(cfg, data["x0"], loss=mls_mpm.PositionLoss(data["target"]))
assert ti.lang.impl.current_cfg().debug  # Simulator kept this initialisation (same arch, float type, fast_math)
c = data["c"]
L = sim.forward(c)
g = sim.backward()
g_tape = sim.gradient_tape(c, validation=True)
out = {"L": L}

def attempt(fn):
    try:
        fn()
        return ["none", ""]
    except Exception as e:
        return [type(e).__name__, str(e)]

big = c.copy()
big[3, 45, 0, 0] = 1e39  # finite in float64, Inf once stored as float32
out["control 1e39"] = attempt(lambda: sim.forward(big))
F = np.tile(np.eye(2), (len(data["x0"]), 1, 1))
F[45, 1, 1] = 1e39
out["initial F 1e39"] = attempt(lambda: (sim.set_initial(data["x0"], F=F), sim.forward(c)))
np.savez(sys.argv[2], g=g, g_tape=g_tape)
print(json.dumps(out))
'''


@pytest.fixture(scope="module")
def float32_run(base, tmp_path_factory):
    """The base scene's float64 gradient here, and in a subprocess (Taichi re-initialised for float32 there,
    which would invalidate this session's fields) the float32 gradient, the float32 Tape with validation and
    the float32 overflow probes."""
    base.reset()
    L64 = base.sim.forward(base.c)
    g64 = base.sim.backward()
    d = tmp_path_factory.mktemp("float32")
    np.savez(d / "in.npz", x0=base.x0, target=base.target, c=base.c, steps=BASE_STEPS, stride=BASE_STRIDE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    run = subprocess.run([sys.executable, "-c", FLOAT32_SCRIPT, str(d / "in.npz"), str(d / "out.npz")], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    arrays = np.load(d / "out.npz")
    return dict(out, L64=L64, g64=g64, g32=arrays["g"], g32_tape=arrays["g_tape"])


@pytest.mark.slow
def test_float32_gradient_against_float64(float32_run, capsys):
    """The 120-step base scene in float32 vs float64, same inputs. Per horizon (control k acts over 120 - 10 k
    steps): float32 manual vs float32 Tape (run with validation=True in debug mode, bounds-checked) <= 1e-4;
    float32 vs float64 gradient <= 1e-3 (measured: 4e-6 at 10 steps to 6e-5 at 90 steps).
    Prints the table (run with -s)."""
    r = float32_run
    g64, g32, g32t = r["g64"], r["g32"], r["g32_tape"]
    assert np.all(np.isfinite(g32)) and np.all(np.isfinite(g32t))
    assert rel_err(r["L"], r["L64"]) <= 1e-5
    rows = []
    for k in range(len(g64) - 1, -1, -1):
        rows.append((BASE_STEPS - k * BASE_STRIDE, np.linalg.norm(g64[k]), rel_err(g32[k], g64[k]),
                     rel_err(g32[k], g32t[k])))
    with capsys.disabled():
        print(f"\nfloat32 vs float64, loss {r['L']:.7e} vs {r['L64']:.7e} (rel {rel_err(r['L'], r['L64']):.1e}); "
              f"whole gradient rel diff {rel_err(g32, g64):.2e}")
        print(f"{'steps':>6} {'|g| f64':>12} {'f32 vs f64':>11} {'f32 vs f32 Tape':>16}")
        for h, n, e64, et in rows:
            print(f"{h:>6} {n:>12.4e} {e64:>11.2e} {et:>16.2e}")
    for h, _, e64, et in rows:
        assert et <= 1e-4, h
        assert e64 <= 1e-3, h


@pytest.mark.slow
def test_float32_overflowing_control_is_refused(float32_run):
    """In float32 a control of 1e39 (finite in float64) becomes Inf: refused up front like a NaN, with a
    ValueError naming control 3 (step 30) and particle 45."""
    kind, msg = float32_run["control 1e39"]
    assert kind == "ValueError" and msg.startswith("controls: control 3 (step 30), particle 45"), (kind, msg)


@pytest.mark.slow
def test_float32_overflowing_initial_state_is_named(float32_run):
    """In float32 an initial F entry of 1e39 becomes Inf: refused with a ValueError (set_initial) or a
    SimulationError at step 0 (check_particle names the earliest step with a fault), naming particle 45."""
    kind, msg = float32_run["initial F 1e39"]
    assert (kind == "ValueError" and msg.startswith("F: particle 45 ")) or \
        (kind == "SimulationError" and msg.startswith("step 0: particle 45 ")), (kind, msg)

