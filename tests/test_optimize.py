"""Optimizers (mls_mpm/optimize.py): each one lowers the loss of a tiny scene, gd's restart from step k * stride
equals a full re-simulation, and an interrupted optimizer resumed from its checkpoint state ends exactly where an
uninterrupted one does.

One Simulator (tests/data/tiny.toml: 32 x 32 grid, ~300 particles, 20 steps, stride 5, K = 4 controls) serves the
whole module; the optimizers themselves take milliseconds here, the kernels' compilation seconds.
"""
import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

from mls_mpm import SimConfig, problem, runtime
from mls_mpm.optimize import METHODS, adam, gd, lbfgs, positions
from mls_mpm.scene import load_scene
from mls_mpm.simulator import Simulator

from conftest import StopAt

TINY = Path(__file__).resolve().parent / "data" / "tiny.toml"


def quiet(*_):
    pass


@pytest.fixture(scope="module")
def scene():
    return load_scene(TINY)


@pytest.fixture(scope="module")
def sim(scene):
    # a fresh Taichi runtime (CPU, float64, as conftest.py sets it): Taichi's offline cache only serves the fields
    # of a fresh runtime, so this loads the ~10 s of reverse kernels from the cache instead of compiling them
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))
    prob = problem.build(scene)
    s = Simulator(scene.sim, prob.x0, loss=prob.loss)
    assert s.cfg.n_controls == 4 and 100 <= s.n_particles <= 400, "tests/data/tiny.toml is no longer tiny"
    return s


def settings(scene, **changes):
    return dataclasses.replace(scene.optimize, **changes)


def scramble(sim, seed=7):
    """Overwrite every stored step with an unrelated trajectory, so a result cannot lean on leftovers."""
    sim.forward(0.05 * np.random.default_rng(seed).standard_normal(sim.control_shape))


# ---------------------------------------------------------------------------------------------------------
# Each optimizer lowers the loss. Factors measured on tiny.toml (initial loss 2.03e-2), with margin:
#   gd normalized, lr 0.1, 3 iterations: 0.45     gd raw, lr 50, 3 iterations: 0.28
#   adam, lr 0.05, 3 steps: 0.23                  lbfgs, 3 steps: 0.15          positions, lr 0.1, 3 steps: 0.44

CASES = {
    "gd_normalized": ("gd", dict(step="normalized", lr=0.1), 0.6),
    "gd_raw": ("gd", dict(step="raw", lr=50.0), 0.45),
    "adam": ("adam", dict(lr=0.05), 0.4),
    "lbfgs": ("lbfgs", dict(), 0.3),
    "positions": ("positions", dict(lr=0.1), 0.6),
}


@pytest.mark.parametrize("case", list(CASES))
def test_optimizer_reduces_loss(sim, scene, case):
    method, changes, factor = CASES[case]
    scramble(sim)
    L0 = sim.forward(sim.zero_controls())
    res = METHODS[method](sim, sim.zero_controls(), settings(scene, iterations=3, tol=0.0, **changes), emit=quiet)
    assert res.losses[0] == L0, "losses[0] is not the loss of the starting controls"
    assert res.iterations == 3 and len(res.losses) == 4 and res.reason == "iteration budget"
    assert not res.converged
    assert res.losses[-1] < factor * L0, f"{case}: loss {L0:.4e} -> {res.losses[-1]:.4e}, expected < {factor} x"
    if method == "positions":
        # controls untouched; the reported loss is that of the returned final positions
        assert np.array_equal(res.controls, sim.zero_controls())
        assert res.positions.shape == (sim.n_particles, 2)
        assert sim.evaluate_positions(res.positions)[0] == res.losses[-1]
    else:
        assert res.controls.shape == sim.control_shape and np.all(np.isfinite(res.controls))
        # the reported final loss is exactly the loss of the returned controls
        assert sim.forward(res.controls) == res.losses[-1]
    if method == "gd":
        # a sufficient-decrease line search never accepts a step that raises the loss
        assert all(b <= a for a, b in zip(res.losses, res.losses[1:])), res.losses


def test_gd_raw_and_normalized_steps_differ(sim, scene):
    """`step` is honoured: a raw step of lr 0.1 along g (|g| ~ 1e-2) moves the controls far less than a normalized one."""
    raw = gd(sim, sim.zero_controls(), settings(scene, iterations=1, step="raw", lr=0.1, tol=0.0), emit=quiet)
    nrm = gd(sim, sim.zero_controls(), settings(scene, iterations=1, step="normalized", lr=0.1, tol=0.0), emit=quiet)
    # normalized: every control that moved took a step of length lr * 2^-j along g / |g|
    for k in range(sim.cfg.n_controls):
        n = np.linalg.norm(nrm.controls[k])
        if n:
            j = np.log2(0.1 / n)
            assert abs(j - round(j)) < 1e-9, f"control {k}: step {n} is not 0.1 / 2^j"
    assert np.linalg.norm(raw.controls) < 0.1 * np.linalg.norm(nrm.controls)
    assert raw.losses[-1] < raw.losses[0]


def test_gd_gives_up_when_no_step_decreases(sim, scene):
    """A line search that finds no decrease keeps the controls, restores the stored trajectory, and a whole temporal
    iteration without decrease stops gd (thesis 7.3). On tiny.toml a first step of 30 along g / |g| raises the loss
    for every control without the particles leaving the grid (48 and more do leave it)."""
    L0 = sim.forward(sim.zero_controls())
    res = gd(sim, sim.zero_controls(), settings(scene, iterations=5, lr=30.0, line_search=0, tol=0.0), emit=quiet)
    assert res.converged and res.reason == "no sufficient decrease in a whole temporal iteration"
    assert res.iterations == 1 and res.losses == [L0, L0]
    assert np.array_equal(res.controls, sim.zero_controls())
    # the stored steps (and controls) are those of the kept zero controls again, not of the last rejected trial:
    # a reverse pass over them, with no forward in between, gives the gradient of the zero controls
    g_after = sim.backward(stop=0)
    sim.forward(sim.zero_controls())
    assert np.array_equal(g_after, sim.backward())


def test_gd_line_search_backtracks_from_a_step_that_leaves_the_grid(sim, scene):
    L0 = sim.forward(sim.zero_controls())
    res = gd(sim, sim.zero_controls(), settings(scene, iterations=1, lr=200.0, line_search=15, tol=0.0), emit=quiet)
    # 200 / 2^j for some j <= 15 lowers the loss (steps up to 16 do, see above)
    assert res.losses[-1] < L0
    assert np.all(np.isfinite(res.controls))


def test_gd_tolerance_stops_at_once(sim, scene):
    res = gd(sim, sim.zero_controls(), settings(scene, iterations=5, tol=1e6), emit=quiet)
    assert res.converged and res.reason == "gradient norm below tolerance"
    assert res.iterations == 1 and np.array_equal(res.controls, sim.zero_controls())


# ---------------------------------------------------------------------------------------------------------
# Restart from step k * stride (Algorithm 1): a forward that starts at the stored step k * s and a reverse pass
# that stops there give the same loss and the same gradient of controls >= k as a full re-simulation, bit for bit.

@pytest.mark.parametrize("k", [1, 2, 3])
def test_restart_equals_full_resimulation(sim, k):
    s = sim.cfg.stride
    rng = np.random.default_rng(k)
    c = 0.03 * rng.standard_normal(sim.control_shape)
    c2 = c.copy()
    c2[k:] += 0.03 * rng.standard_normal(c2[k:].shape)

    sim.forward(c)
    L_restart = sim.forward(c2, start=k * s)
    g_restart = sim.backward(stop=k * s)
    L_full = sim.forward(c2)
    g_full = sim.backward()

    assert L_restart == L_full
    assert np.array_equal(g_restart[k:], g_full[k:])
    assert np.all(g_restart[:k] == 0.0), "controls acting before the restart step must get no gradient"
    assert np.all(np.abs(g_full[:k]).sum(axis=(1, 2, 3)) > 0)  # the comparison above is not vacuous
    assert np.abs(g_full[k:]).sum() > 0


def test_restart_reuses_stored_steps(sim):
    """forward(start=k s) continues from the stored step k s: controls before k are taken from the earlier pass,
    not from the argument (that is what makes the restart cheaper than a full pass)."""
    k, s = 2, sim.cfg.stride
    rng = np.random.default_rng(11)
    c = 0.03 * rng.standard_normal(sim.control_shape)
    c2 = 0.03 * rng.standard_normal(sim.control_shape)  # differs everywhere, also before k
    hybrid = np.concatenate([c[:k], c2[k:]])
    sim.forward(c)
    L_restart = sim.forward(c2, start=k * s)
    assert L_restart == sim.forward(hybrid)
    assert L_restart != sim.forward(c2)


class FullResimulation:
    """A Simulator whose forward always starts at step 0 and whose reverse pass always runs to step 0."""

    def __init__(self, sim):
        self.sim, self.cfg = sim, sim.cfg

    def forward(self, controls, start=0):
        return self.sim.forward(controls)

    def backward(self, stop=None):
        return self.sim.backward(stop=0)


def test_gd_with_restarts_matches_gd_with_full_resimulation(sim, scene):
    opts = settings(scene, iterations=2, tol=0.0)
    fast = gd(sim, sim.zero_controls(), opts, emit=quiet)
    slow = gd(FullResimulation(sim), sim.zero_controls(), opts, emit=quiet)
    assert np.array_equal(fast.controls, slow.controls)
    assert fast.losses == slow.losses and fast.grad_norms == slow.grad_norms
    assert len(fast.grad_norms) == 2 * sim.cfg.n_controls
    assert fast.losses[-1] < fast.losses[0]


# ---------------------------------------------------------------------------------------------------------
# Interrupt and resume: should_stop() turns true at its n-th call; the optimizer checkpoints and returns; a second
# call with resume=<that checkpoint> (on a simulator whose stored steps were overwritten meanwhile) must end exactly
# where an uninterrupted run ends. gd calls should_stop after every control step (K = 4 per temporal iteration)
# and once more after each temporal iteration; adam and positions after every step, lbfgs after every iteration.

def interrupted_then_resumed(sim, method, opts, n):
    saved = []
    first = method(sim, sim.zero_controls(), opts, on_checkpoint=lambda st: saved.append(copy.deepcopy(st)),
                   should_stop=StopAt(n), emit=quiet)
    assert first.reason == "interrupted" and not first.converged
    assert saved, "an interrupted optimizer must leave a checkpoint"
    scramble(sim)
    return method(sim, sim.zero_controls(), opts, emit=quiet, resume=saved[-1]), saved[-1]


def same_result(a, b):
    assert (a.iterations, a.converged, a.reason) == (b.iterations, b.converged, b.reason)
    assert np.array_equal(a.controls, b.controls)
    assert a.losses == b.losses
    assert a.grad_norms == b.grad_norms
    if a.positions is not None or b.positions is not None:
        assert np.array_equal(a.positions, b.positions)


K_BOUNDARY_BUG = ("bug: gd interrupted after the last control step of a temporal iteration checkpoints k = K; "
                  "resumed, its inner loop does not run, `small` stays True and it stops as 'converged' "
                  "(optimize.py gd: keep `small` in the checkpointed state like `improved`)")


@pytest.mark.parametrize("n", [
    1,  # after control 0 of iteration 1
    2,  # after control 1 of iteration 1
    4,  # after control 3 = K - 1 (k = K is checkpointed; the iteration's bookkeeping runs on resume)
    5,  # after iteration 1's bookkeeping (k = 0 of iteration 2)
    7,  # after control 1 of iteration 2
])
def test_gd_resume_equals_uninterrupted(sim, scene, n):
    opts = settings(scene, iterations=3, tol=0.0)
    scramble(sim)
    whole = gd(sim, sim.zero_controls(), opts, emit=quiet)
    resumed, state = interrupted_then_resumed(sim, gd, opts, n)
    assert state["iteration"] * sim.cfg.n_controls + state["k"] in (n, n - 1)  # where it stopped
    same_result(resumed, whole)


@pytest.mark.parametrize("method", [adam, positions, lbfgs], ids=["adam", "positions", "lbfgs"])
@pytest.mark.parametrize("n", [1, 2])
def test_resume_equals_uninterrupted(sim, scene, method, n):
    opts = settings(scene, iterations=3, tol=0.0, lr=0.05)
    scramble(sim)
    whole = method(sim, sim.zero_controls(), opts, emit=quiet)
    resumed, state = interrupted_then_resumed(sim, method, opts, n)
    assert state["iteration"] == n
    same_result(resumed, whole)


@pytest.mark.parametrize("n", [1, 2])
def test_lbfgs_resume_equals_uninterrupted(sim, scene, n):
    """L-BFGS's checkpoint holds its whole state (iterate, loss, gradient, curvature pairs in order): resumed after
    iteration n of 4, it ends exactly where an uninterrupted run ends."""
    opts = settings(scene, iterations=4, tol=0.0)
    scramble(sim)
    whole = lbfgs(sim, sim.zero_controls(), opts, emit=quiet)
    resumed, state = interrupted_then_resumed(sim, lbfgs, opts, n)
    assert state["iteration"] == n and len(state["S"]) == n and state["S"].shape == (n, whole.controls.size)
    same_result(resumed, whole)


def test_gd_checkpoints_after_every_control_step(sim, scene):
    """gd saves its state after each control step, not only after a temporal iteration: a run killed in the
    middle of a temporal iteration (no interrupt: the last checkpoint written is all a resume has) continues
    exactly."""
    opts = settings(scene, iterations=2, tol=0.0)
    K = sim.cfg.n_controls
    saved = []
    scramble(sim)
    whole = gd(sim, sim.zero_controls(), opts, emit=quiet, on_checkpoint=lambda st: saved.append(copy.deepcopy(st)))
    # K control steps and one bookkeeping point per temporal iteration
    assert [(st["iteration"], st["k"]) for st in saved] == [(0, 1), (0, 2), (0, 3), (0, 4), (1, 0),
                                                            (1, 1), (1, 2), (1, 3), (1, 4), (2, 0)]
    assert K == 4
    for st in (saved[1], saved[6]):  # after control 1 of iteration 1, after control 1 of iteration 2
        scramble(sim)
        same_result(gd(sim, sim.zero_controls(), opts, emit=quiet, resume=copy.deepcopy(st)), whole)


@pytest.mark.parametrize("method", list(METHODS))
def test_zero_iterations_return_the_starting_controls(sim, scene, method):
    """optimize.iterations = 0: the starting controls, their loss, and the budget as the reason."""
    scramble(sim)
    L0 = sim.forward(sim.zero_controls())
    res = METHODS[method](sim, sim.zero_controls(), settings(scene, iterations=0), emit=quiet,
                          on_checkpoint=lambda st: pytest.fail("a checkpoint without any work"))
    assert res.losses == [L0] and res.iterations == 0 and res.grad_norms == []
    assert (res.converged, res.reason) == (False, "iteration budget")
    assert np.array_equal(res.controls, sim.zero_controls())


def test_lbfgs_stops_at_a_relative_loss_decrease_below_tol(sim, scene):
    """tol: L-BFGS stops once an iteration lowers the loss by less than tol * 1e-3 of the loss before it (tol = 100:
    by less than 10%)."""
    res = lbfgs(sim, sim.zero_controls(), settings(scene, iterations=50, tol=100.0), emit=quiet)
    L = res.losses
    assert res.converged and res.reason == "relative loss decrease below tol * 1e-3"
    assert (L[-2] - L[-1]) < 0.1 * L[-2]
    assert all(a - b >= 0.1 * a for a, b in zip(L[:-2], L[1:-1]))
    assert res.iterations == len(L) - 1 < 50
