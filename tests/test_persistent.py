"""The parallel schedule's passes in one launch (mls_mpm/persistent.py, adjoint/persistent.py): the same states and
gradients as a launch per step, bit for bit, in 2D and 3D; a pass that gives up is run again, and the next ones take a
launch per step for a while; a barrier left alone gives up instead of waiting forever."""
import numpy as np
import pytest
import taichi as ti

import adjoint.persistent
import mls_mpm.persistent
from mls_mpm.bench.child import scene_of
from mls_mpm.simulator import PERSISTENT_BACKOFF, Simulator

CASES = {2: dict(dtype="f64", n_grid=32, particles=1000, steps=20),
         3: dict(dim=3, dtype="f64", n_grid=16, particles=1500, steps=6)}
LAUNCH_PER_STEP = 10 ** 9  # Simulator._persistent_wait: every pass with run_parallel


def problem(dim, threads):
    case = CASES[dim]
    cfg, x0, loss, controls = scene_of(case, case["steps"])
    sim = Simulator(cfg.replace(schedule="parallel", threads=threads), x0, loss=loss)
    assert sim.fields.lanes == threads
    return sim, controls


def gradient_pass(sim, controls, wait):
    """Loss, final state, dL/dF_pc and dL/dx_0 of one forward and backward with Simulator._persistent_wait = wait."""
    sim._persistent_wait = wait
    L = sim.forward(controls)
    g = sim.backward()
    return L, sim.state(sim.cfg.steps), g, sim.grad_x0


def assert_identical(a, b):
    La, sa, ga, xa = a
    Lb, sb, gb, xb = b
    assert La == Lb
    for key in sa:
        assert np.array_equal(sa[key], sb[key]), key
    assert np.array_equal(ga, gb) and np.array_equal(xa, xb)
    assert np.abs(ga).max() > 0


@pytest.mark.parametrize("dim", [2, 3])
def test_one_launch_equals_a_launch_per_step(dim):
    """Two lanes: forward and backward in one launch each give the states, loss and gradients of run_parallel and
    run_parallel_reverse exactly (the same bodies over the same shares). A pass that gave up (other work on the CPUs,
    s.sync[1], as under pytest-xdist on 2 cores) was run with a launch per step, whose results must match too; the
    one-launch pass is tried up to 5 times, and the test is skipped if every try gave up
    (test_one_lane_counts_every_barrier runs the one-launch kernels whatever the load)."""
    sim, controls = problem(dim, 2)
    reference = gradient_pass(sim, controls, LAUNCH_PER_STEP)
    for _ in range(5):
        assert_identical(gradient_pass(sim, controls, 0), reference)
        if sim._persistent_wait == 0:  # neither pass gave up: both ran in one launch
            return
    pytest.skip("every one-launch pass gave up: other work held the CPUs")


def test_one_lane_counts_every_barrier():
    """One lane (threads = 1, schedule parallel) never waits: the pass finishes in one launch with 2 arrivals a step
    (after the scatter and after the grid loop), plus the reverse pass's first one, and equals run_parallel's."""
    sim, controls = problem(2, 1)
    steps = sim.cfg.steps
    reference = gradient_pass(sim, controls, LAUNCH_PER_STEP)
    sim._persistent_wait = 0
    L = sim.forward(controls)
    assert sim.fields.sync.to_numpy().tolist() == [2 * steps, 0, 0]
    g = sim.backward()
    assert sim.fields.sync.to_numpy().tolist() == [2 * steps + 1, 0, 0]  # + the velocity slot's barrier
    assert_identical((L, sim.state(steps), g, sim.grad_x0), reference)


def test_a_pass_that_gave_up_is_run_again_and_the_next_ones_wait(monkeypatch):
    """A one-launch pass that stops halfway with the give-up flag set and junk in the private grids and the gradient
    (as after a barrier timed out) is run again with a launch per step: the same results exactly. The next
    PERSISTENT_BACKOFF passes take a launch per step; the one after tries one launch again."""
    sim, controls = problem(2, 2)
    reference = gradient_pass(sim, controls, LAUNCH_PER_STEP)
    s = sim.fields
    calls = []

    def forward_gives_up(s_, f0, f1):
        calls.append("forward")
        run_persistent(s_, f0, (f0 + f1) // 2)
        s_.lane_mp.fill(7.0)
        s_.sync[1] = 1

    def reverse_gives_up(s_, a, f0, f1):
        calls.append("reverse")
        run_persistent_reverse(s_, a, (f0 + f1) // 2, f1)
        a.lane_adj_v.fill(-3.0)
        a.adj_F_pc.fill(5.0)
        s_.sync[1] = 1

    run_persistent = mls_mpm.persistent.run_persistent
    run_persistent_reverse = adjoint.persistent.run_persistent_reverse
    monkeypatch.setattr(mls_mpm.persistent, "run_persistent", forward_gives_up)
    monkeypatch.setattr(adjoint.persistent, "run_persistent_reverse", reverse_gives_up)
    got = gradient_pass(sim, controls, 0)
    assert calls == ["forward"]  # the forward gave up: the backward already waits
    assert sim._persistent_wait == PERSISTENT_BACKOFF - 1
    assert_identical(got, reference)
    assert int(s.sync[1]) == 1
    for _ in range(PERSISTENT_BACKOFF - 1):
        sim.forward(controls)
    assert calls == ["forward"] and sim._persistent_wait == 0
    sim.forward(controls)
    assert calls == ["forward", "forward"]
    sim._persistent_wait = 0
    g = sim.backward()
    assert calls[-1] == "reverse" and sim._persistent_wait == PERSISTENT_BACKOFF
    assert np.array_equal(g, reference[2])


@ti.data_oriented
class Lone:
    def __init__(self):
        self.sync = ti.field(ti.i32, shape=3)


@ti.kernel
def wait_alone(s: ti.template()) -> ti.i32:
    alive = 1
    for _ in range(1):
        alive = mls_mpm.persistent.barrier(s, 2)
    return alive


def test_a_barrier_left_alone_gives_up():
    """A barrier that waits for two arrivals with one thread (as when fewer threads run than lanes) gives up after
    GIVE_UP_SPINS spins, sets the flag and counts its slow wait, instead of hanging the process."""
    s = Lone()
    assert wait_alone(s) == 0
    assert s.sync.to_numpy().tolist() == [1, 1, 1]
