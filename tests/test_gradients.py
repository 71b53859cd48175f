"""Whole-trajectory gradients dL/dF_pc (thesis section 6, eq 41-71) of a short simulation.

Scene (conftest.scene_config): 32x32 grid, ~290 particles in a disk, 30 steps of dt = 1e-3, stride 10
(K = 3 controls), gravity, slip walls (never reached), drag gamma = 2, random controls of size 0.05. Its 3D
twin (the tests parametrized by dim): a 16^3 grid, ~140 particles in a ball, 12 steps, stride 4 (K = 3),
the loss grids halved (16 and 8 per axis), the same losses, tolerances and checks; its Tape runs in one child
process for all the 3D losses, started in the background when this module starts (Simulator.gradient_tape and
mls_mpm.tape: Taichi's autodiff of the 3D stencil loop needs matrices scalarized, which this session is not).

Tolerances:
- hand-written reverse pass vs ti.ad.Tape on the same forward kernels: rel err <= 1e-6 (both exact up to
  float64 round-off accumulated over 30 steps; observed ~1e-14);
- vs central differences (L(c + eps d) - L(c - eps d)) / 2 eps along random unit directions d, eps = 1e-6:
  rel err <= 1e-5 (truncation ~eps^2, cancellation ~1e-16 |L| / eps).
"""
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import mls_mpm
from conftest import blob, body, random_controls, random_unit, rel_err, scene_config
from mls_mpm import ot
from mls_mpm.tape import tape_gradient, tape_gradients_in_child, tape_state

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

TAPE_TOL = 1e-6
FD_TOL = 1e-5
EPS = 1e-6
ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ problems
def disk_mass(res, center, radius, density=1.0):
    """Target node masses of a uniform disk (2D) or ball (3D: a center of three numbers) on a loss grid of res
    nodes per axis (node [i, j(, k)] at (i, j(, k)) / res)."""
    h = 1.0 / res
    dim = len(center)
    nodes = np.moveaxis(np.indices((res,) * dim) * h, 0, -1)
    r = np.linalg.norm(nodes - np.asarray(center), axis=-1)
    inside = np.clip((radius - r) / h + 0.5, 0.0, 1.0)  # soft edge, one cell wide
    return density * h ** dim * inside


def ramp(res, dim):
    """A colour ramp over the loss grid, turned by 90 degrees from the body's (x, y, 1 - x): (j, i, 1/2) / res."""
    i = np.indices((res,) * dim) / res
    return np.stack([i[1], i[0], 0.5 + 0 * i[0]], axis=-1)


def make_problem(kind, schedule="auto", dim=2):
    cfg = scene_config(schedule=schedule, dim=dim)
    x0 = body(dim)
    N = len(x0)
    fine, coarse = (32, 16) if dim == 2 else (16, 8)  # the loss grids
    z = () if dim == 2 else (0.5,)  # the 3D problems: the 2D ones in the middle plane z = 0.5
    center, radius = (0.53, 0.47) + z, 0.13 if dim == 2 else 0.17
    if kind == "position":
        theta = 0.2
        R = np.eye(dim)
        R[:2, :2] = [[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]]
        loss = mls_mpm.PositionLoss((x0 - 0.5) @ R.T * 1.1 + 0.5 + np.array([0.03, -0.02, 0.01][:dim]))
    elif kind == "mass":
        t32, t16 = disk_mass(fine, center, radius), disk_mass(coarse, center, radius)
        alpha16 = np.where(t16 > 0, 1.0, 3.0)  # penalty grid (eq 72): extra weight where the target is empty
        loss = mls_mpm.MassLoss([t32, t16], weights=[1.0, 0.5], alpha=[None, alpha16])
    elif kind == "log_mass":
        # density 40 (as in the shipped scenes): node masses ~0.04, so ln(m + 1) keeps its digits; at density 1
        # (m ~ 1e-3) computing ln(m + 1) loses ~3 digits and central differences hit that noise floor
        cfg = cfg.replace(density=40.0)
        loss = mls_mpm.MassLoss([disk_mass(fine, center, radius, density=40.0)], log=True)
    elif kind == "color":
        colors = np.stack([x0[:, 0], x0[:, 1], 1.0 - x0[:, 0]], axis=1)  # a color ramp over the body
        t32 = disk_mass(fine, center, radius)
        loss = mls_mpm.ColorLoss([t32[..., None] * ramp(fine, dim)], colors=colors)  # the ramp turned by 90 degrees
    elif kind == "ot":
        # balanced Sinkhorn divergence on a 16 grid, target offset by ~5 cells of it (far beyond eq 11's reach)
        # plus eq 11 on the 32 grid; Sinkhorn run to 1e-12 so that its potentials are exact to round-off
        far = (0.70, 0.62) if dim == 2 else (0.64, 0.58, 0.5)
        loss = mls_mpm.OTLoss([disk_mass(coarse, far, radius), disk_mass(fine, far, radius)], weights=[1.0, 0.5],
                              blur=1.5, mass_weights=[0.0, 2.0], tol=1e-12)
    elif kind == "color_ot":
        # colour transport per channel on a 16 grid (the ramp turned by 90 degrees, as "color"), eq 13 on a 32 grid
        colors = np.stack([x0[:, 0], x0[:, 1], 1.0 - x0[:, 0]], axis=1)
        targets = [disk_mass(r, center, radius)[..., None] * ramp(r, dim) for r in (coarse, fine)]
        loss = mls_mpm.ColorLoss(targets, colors, weights=[0.0, 1.0], ot_weights=[1.0, 0.0], blur=1.5, tol=1e-12)
    elif kind == "ot_unbalanced":
        loss = mls_mpm.OTLoss([disk_mass(coarse, (0.6, 0.55) + z, 0.1 if dim == 2 else 0.15, density=2.0)],
                              blur=1.5, reach=0.3, tol=1e-12)
    else:
        raise ValueError(kind)
    sim = mls_mpm.Simulator(cfg, x0, loss=loss)
    return sim, x0, random_controls(sim.control_shape, 0.05, seed=N)


class Problems(dict):
    """Simulators built on first use and kept for the module (each compiles its kernels once); a key is a loss
    kind (2D) or (kind, dim)."""

    def __getitem__(self, key):
        return super().__getitem__((key, 2) if isinstance(key, str) else key)

    def __missing__(self, key):
        kind, dim = key
        self[key] = make_problem(kind, dim=dim)
        return self[key]


@pytest.fixture(scope="module")
def problems():
    return Problems()


@pytest.fixture(scope="module", autouse=True)
def tapes_3d(request, problems):
    """{kind: Tape gradient} of the 3D problems (KINDS_3D), from one child process (mls_mpm.tape) that compiles and
    runs their Tapes on one core while this module's other tests run (about 90 s: the problems share one scene and
    body, so one tape_state and one compile of the trajectory's Tape kernels); not started when no test of this
    session needs it."""
    if not any(item.name.startswith("test_manual_gradient_matches_tape_3d") for item in request.session.items):
        yield None
        return
    jobs = [(sim.cfg, sim.state(0), sim.loss, c) for sim, _, c in (problems[k, 3] for k in KINDS_3D)]
    pool = ThreadPoolExecutor(1)
    future = pool.submit(tape_gradients_in_child, jobs)
    yield lambda kind: future.result()[KINDS_3D.index(kind)][1]
    pool.shutdown(wait=True)


@pytest.fixture(scope="module")
def tape_2d(problems):
    """One tape_state for the 2D problems of TAPE_SHARED: their Tapes compile the trajectory's kernels once (about
    20 s cold) and each loss only its own loss kernels."""
    sim, x0, _ = problems["position"]
    return tape_state(sim.cfg, len(x0), [problems[k][0].loss for k in TAPE_SHARED])


def fd_directional(sim, c, d, eps=EPS):
    return (sim.forward(c + eps * d) - sim.forward(c - eps * d)) / (2 * eps)


KINDS = ["position", "mass", "log_mass", "color", "ot", "ot_unbalanced", "color_ot"]
# 3D: the losses whose kernels differ (particles, mass grids with a penalty, colour grids, transport); each 3D
# problem compiles its own step kernels (about 16 s compiled fast on 2 cores), so the log mass, unbalanced and colour
# transport variants, which differ from these in their numpy or per-node seed only, run in 2D
KINDS_3D = ["position", "mass", "color", "ot"]
TAPE_SHARED = [k for k in KINDS if k != "log_mass"]  # one scene and body (log_mass's runs at density 40)
DIM = pytest.mark.parametrize("dim", [2, 3], ids=["2d", "3d"])
# The OT losses' directional derivatives are small (~1e-6 and ~1e-8 of losses ~0.04 and ~4e-4), so at eps = 1e-6
# the cancellation error 1e-16 |L| / eps is ~1e-5 of them; at 1e-4 it is ~1e-7 and the truncation ~eps^2 below it.
FD_EPS = {"ot": 1e-4, "ot_unbalanced": 1e-4, "color_ot": 1e-4}


# ------------------------------------------------------------------ manual vs Tape vs finite differences
@pytest.mark.parametrize("kind", ["position", "mass", "ot", pytest.param("log_mass", marks=pytest.mark.slow),
                                  pytest.param("color", marks=pytest.mark.slow),
                                  pytest.param("ot_unbalanced", marks=pytest.mark.slow),
                                  pytest.param("color_ot", marks=pytest.mark.slow)])
def test_manual_gradient_matches_tape(request, problems, kind, dim=2):
    """backward() (eq 41-71) vs ti.ad.Tape over the same p2g/grid_op/g2p and loss kernels: rel err <= 1e-6.

    Losses: position (eq 10); mass on a 32 and a 16 grid with weights 1, 0.5 and a penalty grid alpha on the
    16 grid (eq 11, 72); log mass; color (eq 12-13); transport. The Tapes of the losses on the test scene share
    one tape_state (tape_2d); log mass, at another density, runs Simulator.gradient_tape, which compiles its own
    grad-enabled Tape state (~20 s cold; test_isotropic_deformation_gradient runs it too). The cases marked slow
    have their seeds checked against the Tape in test_adjoint_kernels.py and their whole trajectories against
    central differences below.
    """
    sim, _, c = problems[kind, dim]
    L = sim.forward(c)
    g = sim.backward()
    if kind in TAPE_SHARED:
        g_tape = tape_gradient(sim.cfg, sim.state(0), sim.loss, c, state=request.getfixturevalue("tape_2d"))[1]
    else:
        g_tape = sim.gradient_tape(c)
    assert L > 0.0 and np.all(np.isfinite(g))
    assert rel_err(g, g_tape) <= TAPE_TOL
    # every control step receives gradient (a reverse pass that stopped early would leave zeros)
    assert all(np.linalg.norm(g[k]) > 1e-3 * np.linalg.norm(g) for k in range(len(g)))


@pytest.mark.parametrize("kind, dim", [(k, 2) for k in KINDS] + [(k, 3) for k in KINDS_3D],
                         ids=[f"{k}-2d" for k in KINDS] + [f"{k}-3d" for k in KINDS_3D])
def test_manual_gradient_matches_central_differences(problems, kind, dim):
    """<dL/dF_pc, d> vs central differences along 2 random unit directions: rel err <= 1e-5."""
    sim, _, c = problems[kind, dim]
    sim.forward(c)
    g = sim.backward()
    for q in range(2):
        d = random_unit(c.shape, seed=100 + q)
        assert rel_err(np.sum(g * d), fd_directional(sim, c, d, FD_EPS.get(kind, EPS))) <= FD_TOL
    # the gradient direction itself: a descent step along -g lowers the loss by about eps |g|^2
    d = g / np.linalg.norm(g)
    assert rel_err(np.linalg.norm(g), fd_directional(sim, c, d, FD_EPS.get(kind, EPS))) <= FD_TOL


@pytest.mark.parametrize("a, dim", [(1.0, 2), (1.2, 2), (0.85, 2), (1.0, 3), (1.2, 3), (0.85, 3)],
                         ids=["rest F=I-2d", "F=1.2I-2d", "F=0.85I-2d", "rest F=I-3d", "F=1.2I-3d", "F=0.85I-3d"])
def test_isotropic_deformation_gradient(problems, a, dim):
    """Zero controls except F_pc^0 = (a - 1) I, so F + F_pc = a I at step 0 (a = 1: the rest state, P(I) = 0).

    At these F the polar rotation is R = I and every singular value is repeated, where a careless derivative of
    eq 9 (2D: the polar angle; 3D: an SVD's 1 / (s_i^2 - s_j^2)) divides by zero.
    Finite, and Tape rel err <= 1e-6 (2D), central differences rel err <= 1e-5 (position loss).
    """
    sim, _, c = problems["position", dim]
    c = np.zeros_like(c)
    c[0] = (a - 1.0) * np.eye(dim)
    sim.forward(c)
    if a != 1.0:
        F1 = sim.state(1)["F"]
        assert rel_err(F1, np.broadcast_to(a * np.eye(dim), F1.shape)) < 0.05  # (I + dt C) a I, dt C small
    g = sim.backward()
    assert np.all(np.isfinite(g))
    if dim == 2:  # the Tape differentiates the 2D kernels only (Simulator.gradient_tape)
        assert rel_err(g, sim.gradient_tape(c)) <= TAPE_TOL
    for q in range(2):
        d = random_unit(c.shape, seed=200 + q)
        assert rel_err(np.sum(g * d), fd_directional(sim, c, d)) <= FD_TOL


def test_ot_loss_vanishes_on_its_own_masses_and_descends_toward_a_far_target():
    """The balanced OT loss of a Simulator (16 grid, blur 1.5 cells) on the test scene with random controls.

    Far target (a disk ~0.2 away, beyond eq 11's reach): the loss is finite and > 0, and a step h = 0.01 along
    -g / |g| lowers it by h |g| to 1% (the gradient's sign and size); most particles end closer to the target's
    centre, the centroid staying put (the controls are internal forces). Target = the body's own final loss-grid
    masses (same controls): the debiased divergence and its seed are 0, below 1e-10 of those for the target
    shifted by 2 cells.
    """
    cfg, x0 = scene_config(), blob()
    centre = np.array([0.70, 0.62])
    sim = mls_mpm.Simulator(cfg, x0, loss=mls_mpm.OTLoss([disk_mass(16, centre, 0.13)], blur=1.5))
    c = random_controls(sim.control_shape, 0.05, seed=len(x0))
    L0 = sim.forward(c)
    x_before = sim.state(cfg.steps)["x"]
    own = sim.fields.loss_grids[0].m.to_numpy()[..., 0].copy()
    far_seed = np.abs(sim.fields.loss_grids[0].seed.to_numpy()).max()
    g = sim.backward()
    assert np.isfinite(L0) and L0 > 0 and np.all(np.isfinite(g)) and np.linalg.norm(g) > 0
    h = 0.01
    L1 = sim.forward(c - h * g / np.linalg.norm(g))
    assert L1 < L0 and rel_err(L1 - L0, -h * np.linalg.norm(g)) <= 0.01
    x_after = sim.state(cfg.steps)["x"]
    closer = np.linalg.norm(x_after - centre, axis=1) < np.linalg.norm(x_before - centre, axis=1)
    assert closer.mean() > 0.6
    assert np.linalg.norm(x_after.mean(axis=0) - x_before.mean(axis=0)) < 1e-12

    shifted = ot.sinkhorn_divergence(own, np.roll(own, 2, axis=0), 1.5 / 16)
    assert shifted.value == pytest.approx(0.5 * (2 / 16) ** 2, rel=1e-3)  # a translation costs |shift|^2 / 2
    same = mls_mpm.Simulator(cfg, x0, loss=mls_mpm.OTLoss([own], blur=1.5))
    assert abs(same.forward(c)) <= 1e-10 * shifted.value
    assert np.abs(same.fields.loss_grids[0].seed.to_numpy()).max() <= 1e-10 * far_seed


@DIM
def test_initial_state_gradients(problems, dim):
    """grad_x0 = dL/dx_p^0 and grad_v0 = dL/dv_p^0 (eq 69, 71 at step 0) vs central differences of the
    initial state (set_initial), rel err <= 1e-5, at a state with random v0 and controls.

    Sign: the position target lies right of the body (+0.03 in x), so moving or pushing every particle
    right lowers the loss: the x-components of both gradients sum to a negative number.
    """
    sim, x0, c = problems["position", dim]
    rng = np.random.default_rng(3)
    v0 = 0.1 * rng.standard_normal(x0.shape)
    try:
        sim.set_initial(x0, v=v0)
        sim.forward(c)
        sim.backward()
        gx, gv = sim.grad_x0, sim.grad_v0
        assert np.sum(gx[:, 0]) < 0.0 and np.sum(gv[:, 0]) < 0.0
        for q in range(2):
            d = random_unit(x0.shape, seed=300 + q)
            sim.set_initial(x0 + EPS * d, v=v0)
            Lp = sim.forward(c)
            sim.set_initial(x0 - EPS * d, v=v0)
            Lm = sim.forward(c)
            assert rel_err(np.sum(gx * d), (Lp - Lm) / (2 * EPS)) <= FD_TOL
            sim.set_initial(x0, v=v0 + EPS * d)
            Lp = sim.forward(c)
            sim.set_initial(x0, v=v0 - EPS * d)
            Lm = sim.forward(c)
            assert rel_err(np.sum(gv * d), (Lp - Lm) / (2 * EPS)) <= FD_TOL
    finally:
        sim.set_initial(x0)


@pytest.mark.parametrize("dim, start", [(2, 10), (2, 17), (3, 4), (3, 7)],
                         ids=["2d at control step 10", "2d between controls", "3d at control step 4",
                              "3d between controls"])
def test_restart_reproduces_loss_and_gradient(problems, dim, start):
    """forward(c, start=k) after a full forward(c) recomputes steps k..N_t from the stored step k: the same loss
    and, after backward(), the same dL/dF_pc for controls acting at steps >= k, and zero for earlier ones.

    Exact equality: the 2D scene runs the serial schedule (SimConfig.schedule = "auto" below 4000 particles +
    nodes), which adds in a fixed order; the 3D one the parallel schedule, whose per-thread private grids are
    filled from fixed particle ranges and summed in a fixed order.
    """
    sim, _, c = problems["position", dim]
    L = sim.forward(c)
    g = sim.backward()
    L_restart = sim.forward(c, start=start)
    g_restart = sim.backward()
    assert L_restart == L
    later = np.arange(sim.cfg.n_controls) * sim.cfg.stride >= start
    assert np.array_equal(g_restart[later], g[later])
    assert np.all(g_restart[~later] == 0.0) and np.any(g[~later] != 0.0)


def test_backward_needs_a_successful_forward():
    """backward() before any forward() raised nothing and returned zeros; grad_x0 / grad_v0 before backward()
    raised AttributeError on None. Now each is one RuntimeError saying what to call; so is forward(start=k)
    when step k was never stored. (Refused before any kernel runs: this Simulator compiles nothing.)"""
    cfg = scene_config()
    sim = mls_mpm.Simulator(cfg, blob(), loss=mls_mpm.MassLoss([disk_mass(32, (0.5, 0.5), 0.1)]))
    with pytest.raises(RuntimeError,
                       match=r"^backward\(\): no successful forward pass .*; call forward\(controls\) first$"):
        sim.backward()
    for name in ("grad_x0", "grad_v0"):
        with pytest.raises(RuntimeError, match=rf"^{name}: no successful backward pass .*; call backward\(\) after "
                                               r"forward\(controls\) first$"):
            getattr(sim, name)
    with pytest.raises(RuntimeError, match=r"^forward\(start=10\): step 10 is not stored .* at most 0$"):
        sim.forward(sim.zero_controls(), start=10)


def test_a_failed_forward_is_not_differentiated(problems):
    """After a forward that raised, backward() is refused, and so is a restart after the failed pass's own start;
    a restart at or before that start is exact (its stored steps are intact), and so is a full forward."""
    sim, _, c = problems["position"]
    L = sim.forward(c)
    g = sim.backward()
    bad = c.copy()
    bad[2, 7] = 1e200 * np.eye(2)  # control 2 acts at step 20: P2G's stress overflows there
    with pytest.raises(mls_mpm.SimulationError, match="^step 20: particle 7 "):
        sim.forward(bad, start=10)
    with pytest.raises(RuntimeError, match=r"^backward\(\): no successful forward pass"):
        sim.backward()
    for name in ("grad_x0", "grad_v0"):
        with pytest.raises(RuntimeError, match=rf"^{name}: no successful backward pass"):
            getattr(sim, name)
    with pytest.raises(RuntimeError, match=r"^forward\(start=17\): step 17 is not stored .* at most 10$"):
        sim.forward(c, start=17)
    assert sim.forward(c, start=10) == L  # steps 0..10 were kept
    later = np.arange(sim.cfg.n_controls) * sim.cfg.stride >= 10
    assert np.array_equal(sim.backward()[later], g[later])
    with pytest.raises(mls_mpm.SimulationError):
        sim.forward(bad)
    with pytest.raises(RuntimeError, match=r"^forward\(start=10\): step 10 is not stored .* at most 0$"):
        sim.forward(c, start=10)
    assert sim.forward(c) == L and np.array_equal(sim.backward(), g)


def test_evaluate_positions_writes_only_x(problems):
    """evaluate_positions places x at step N_t and leaves v, C, F of that step as they were (it rewrote all
    four); the stored trajectory no longer ends where the forward pass left it, so backward() is refused."""
    sim, x0, c = problems["position"]
    T = sim.cfg.steps
    sim.forward(c)
    before = sim.state(T)
    x = before["x"] + 0.01
    sim.evaluate_positions(x)
    after = sim.state(T)
    assert np.array_equal(after["x"], x)
    for key in ("v", "C", "F"):
        assert np.array_equal(after[key], before[key]), key
    with pytest.raises(RuntimeError, match=r"^backward\(\): no successful forward pass"):
        sim.backward()
    sim.forward(c)


def test_parallel_schedule_matches_serial(problems):
    """schedule = "parallel" (one launch per step; on a CPU each thread scatters P2G and reverse G2P into its
    own private grid, summed by the grid loop) vs the serial schedule of the same scene: same final state and
    loss to rel err 1e-12 and the same dL/dF_pc to rel err 1e-10 (only the order of additions differs)."""
    sim, x0, c = problems["position"]
    par, _, _ = make_problem("position", schedule="parallel")
    assert not par.cfg.serial(par.n_particles) and par.fields.lanes >= 1
    L, L_par = sim.forward(c), par.forward(c)
    assert rel_err(L_par, L) <= 1e-12
    for key in ("x", "v", "C", "F"):
        assert rel_err(par.state(sim.cfg.steps)[key], sim.state(sim.cfg.steps)[key]) <= 1e-12
    assert rel_err(par.backward(), sim.backward()) <= 1e-10
    assert rel_err(par.grad_x0, sim.grad_x0) <= 1e-10 and rel_err(par.grad_v0, sim.grad_v0) <= 1e-10


VALIDATION_SCRIPT = r"""
import numpy as np, taichi as ti
ti.init(arch=ti.cpu, default_fp=ti.f64, debug=True, offline_cache=False, log_level=ti.ERROR)
import mls_mpm
from mls_mpm import losses
from mls_mpm.grid import grid_op
from mls_mpm.state import State, upload_loss, write_step
from mls_mpm.transfer import g2p, p2g

cfg = mls_mpm.SimConfig(n_grid=16, steps=3, stride=2, dt=1e-3, E=100.0, gamma=2.0)
rng = np.random.default_rng(0)
N = 24
x0 = 0.5 + 0.1 * rng.uniform(-1, 1, (N, 2))
loss = mls_mpm.MassLoss([rng.uniform(0, 2e-3, (16, 16))], alpha=[rng.uniform(1, 3, (16, 16))])
t = State(cfg, N, loss_grids=loss.grids, needs_grad=True)
upload_loss(t, loss)
write_step(t, 0, x0, 0.1 * rng.standard_normal((N, 2)), np.zeros((N, 2, 2)), np.tile(np.eye(2), (N, 1, 1)))

def run(c, tape=False):
    t.F_pc.from_numpy(c)
    for field in (t.grid_mp, t.grid_v, t.loss, *(g.m for g in t.loss_grids)):
        field.fill(0.0)
    def body():
        for f in range(cfg.steps):
            p2g(t, f); grid_op(t, f); g2p(t, f)
        for g in t.loss_grids:
            losses.splat(t, g, cfg.steps); losses.grid_loss(t, g)
    if tape:
        with ti.ad.Tape(loss=t.loss, validation=True):  # raises on a global data access rule violation
            body()
        return t.F_pc.grad.to_numpy()
    body()
    return t.loss[None]

c = 0.05 * rng.standard_normal((cfg.n_controls, N, 2, 2))
d = rng.standard_normal(c.shape)
# differences first: Taichi 1.7.4's Tape leaves a kernel recorded more than once in validation mode after
# it exits, and that kernel then trips over the check bits the Tape's reads left set
fd = (run(c + 1e-6 * d) - run(c - 1e-6 * d)) / 2e-6
g = run(c, tape=True)
print("REL_ERR", abs(np.sum(g * d) - fd) / max(abs(fd), abs(np.sum(g * d))))
"""


@pytest.mark.slow
def test_forward_kernels_pass_tape_validation(tmp_path):
    """ti.ad.Tape(validation=True) over p2g, grid_op, g2p, splat and grid_loss, in a subprocess under
    ti.init(debug=True) (the check needs debug mode, which the rest of the suite does not use): no violation
    of the global data access rule is raised, and the validated Tape gradient agrees with central differences
    of the same kernels, rel err <= 1e-5. About 40 s (debug-mode compilation)."""
    script = tmp_path / "validate.py"
    script.write_text(VALIDATION_SCRIPT)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    err = float(out.stdout.split("REL_ERR")[-1])
    assert err <= FD_TOL


def test_a_tape_state_refuses_a_loss_it_was_not_made_for(problems):
    """tape_state: the Tapes of several losses share one State (tape_gradients_in_child, the 3D Tapes here); a loss
    it holds no grids or targets for is refused, not differentiated against another loss's targets, and so is a
    config (whose constants its kernels compile in) or particle count it was not made for."""
    sim, x0, c = problems["position"]
    t = tape_state(sim.cfg, len(x0), [sim.loss])
    with pytest.raises(ValueError, match="made for other losses"):
        tape_gradient(sim.cfg, sim.state(0), problems["mass"][0].loss, c, state=t)
    with pytest.raises(ValueError, match="made for another config or particle count"):
        tape_gradient(sim.cfg.replace(density=40.0), sim.state(0), sim.loss, c, state=t)


@pytest.mark.parametrize("kind", KINDS_3D)
def test_manual_gradient_matches_tape_3d(problems, tapes_3d, kind):
    """The 3D twin of test_manual_gradient_matches_tape: backward() vs ti.ad.Tape, rel err <= 1e-6, for each loss
    of KINDS_3D (position, mass on 16 and 8 grids with a penalty grid, colour, transport)."""
    sim, _, c = problems[kind, 3]
    sim.forward(c)
    g = sim.backward()
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0.0
    assert rel_err(g, tapes_3d(kind)) <= TAPE_TOL
