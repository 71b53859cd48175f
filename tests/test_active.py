"""The active box (mls_mpm/active.py): with lanes (the CPU's parallel schedule) the grid loops, forward and reverse,
visit only the nodes the step's particles touch. Each step's box is exactly the particles' stencils on the grid, in
one launch a pass and in a launch per step; a pass after the body moved elsewhere gives the loss and gradients of the
first pass on the fresh grid, bit for bit (the earlier pass's nodes outside the box are never read); and grid_mass
shows zero there, although the field still holds that pass's values."""
import numpy as np
import pytest

from mls_mpm.bench.child import scene_of
from mls_mpm.field3d import splat
from mls_mpm.simulator import Simulator

CASES = {2: dict(dtype="f64", n_grid=32, particles=600, steps=12), 3: dict(dim=3, dtype="f64", n_grid=16,
                                                                            particles=700, steps=6)}
LAUNCH_PER_STEP = 10 ** 9  # Simulator._persistent_wait: every pass with run_parallel


@pytest.fixture(scope="module", params=[2, 3])
def problem(request):
    case = CASES[request.param]
    cfg, x0, loss, controls = scene_of(case, case["steps"])
    small = 0.5 + 0.45 * (x0 - 0.5)  # a ball of radius about 0.11: boxes well inside the grid
    shift = np.eye(cfg.dim)[0] * 0.2
    left, right = small - shift, small + shift
    sim = Simulator(cfg.replace(schedule="parallel", threads=2), left, loss=loss)
    assert sim.fields.lanes == 2
    return sim, controls, left, right


def stencil_box(x, n):
    """[lo, hi) of the 4-node stencils of the points x (P, dim) that lie on the grid, in numpy."""
    base = np.floor(x * n).astype(np.int64) - 1
    on = np.all((base >= 0) & (base <= n - 4), axis=1)
    return base[on].min(axis=0), base[on].max(axis=0) + 4


@pytest.mark.parametrize("wait", [0, LAUNCH_PER_STEP], ids=["one launch", "a launch per step"])
def test_each_steps_box_is_its_particles_stencils(problem, wait):
    sim, controls, left, _ = problem
    sim.set_initial(left)
    sim._persistent_wait = wait
    sim.forward(controls)
    box = sim.fields.box.to_numpy()
    n = sim.cfg.n_grid
    for f in range(sim.cfg.steps):
        lo, hi = stencil_box(sim.state(f)["x"], n)
        assert box[f, 0].tolist() == lo.tolist() and box[f, 1].tolist() == hi.tolist(), f
        assert np.prod(hi - lo) < 0.5 * n ** sim.cfg.dim  # the box is the smaller part of the grid here


def test_a_pass_after_the_body_moved_reads_nothing_of_the_earlier_one(problem):
    """right, left, right: the second right pass (after left's values outside its boxes) equals the first (on grids
    that the start of the simulator's life left zero), and grid_mass is the particles' own splat."""
    sim, controls, left, right = problem

    def gradient(x):
        sim.set_initial(x)
        L = sim.forward(controls)
        return L, sim.backward(), sim.grad_x0, sim.fields.grid_mass()

    first = gradient(right)
    gradient(left)
    f = 1  # (the forward clears the whole grid of its first step, 0, before it starts)
    raw = sim.fields.grid_mp.to_numpy()[f, ..., -1]  # step f's m_i as left put it
    again = gradient(right)
    assert first[0] == again[0] and np.abs(first[1]).max() > 0
    assert np.array_equal(first[1], again[1]) and np.array_equal(first[2], again[2])
    assert np.array_equal(first[3], again[3])
    m_p = sim.cfg.m_p
    expected, _ = splat(sim.state(f)["x"], m_p, sim.cfg.n_grid)
    np.testing.assert_allclose(again[3][f], expected, rtol=0, atol=1e-12 * m_p)
    lo, hi = sim.fields.box.to_numpy()[f]
    outside = np.ones(expected.shape, bool)
    outside[tuple(slice(a, b) for a, b in zip(lo, hi))] = False
    stale = sim.fields.grid_mp.to_numpy()[f, ..., -1]
    assert np.array_equal(stale[outside], raw[outside])  # outside right's box the field keeps left's values...
    assert np.abs(raw[outside]).max() > 0.1 * m_p and not again[3][f][outside].any()  # ... which grid_mass hides
