"""Bit-identical results run after run on one machine and thread count, in the parallel schedule.

P2G and reverse G2P scatter into per-thread private grids summed in a fixed order; the loss kernels (the
splat onto the loss grids and the sums of grid_loss / position_loss) run serially on a CPU, since float
atomics from two threads add in the order the threads happen to reach a node. The scene is large enough that
every parallel loop splits between the two threads: 20000 particles in random order (neighbouring indices lie
far apart, so both threads splat onto the same nodes at once). Fault reports are deterministic too: the
earliest step, and in it the lowest particle index (atomic_min), never whichever thread stored first.
"""
import numpy as np
import pytest

import mls_mpm
from conftest import random_controls, scene_config
from mls_mpm.state import write_step

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

N = 20000


def make_sim():
    cfg = scene_config(schedule="parallel", threads=2, steps=4, stride=2, particles_per_cell=64)
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.25, 0.75, (N, 2))
    loss = mls_mpm.MassLoss([rng.uniform(0, 1e-4, (32, 32)), rng.uniform(0, 3e-5, (64, 64))],
                            alpha=[None, rng.uniform(1.0, 2.0, (64, 64))])
    sim = mls_mpm.Simulator(cfg, x0, loss=loss)
    assert sim.fields.lanes == 2 and sim.fields.lane_chunk == N // 2
    return sim, x0


@pytest.fixture(scope="module")
def sim():
    return make_sim()


def run(sim, c):
    L = sim.forward(c)
    return L, sim.backward(), sim.grad_x0, sim.grad_v0


def test_forward_and_backward_are_bit_identical(sim):
    sim, x0 = sim
    c = random_controls(sim.control_shape, 0.05)
    first = run(sim, c)
    for _ in range(2):
        again = run(sim, c)
        assert again[0] == first[0]
        for a, b in zip(again[1:], first[1:]):
            assert np.array_equal(a, b)
    positions = [sim.evaluate_positions(x0 + 0.001) for _ in range(5)]  # the loss and its seed alone
    for L, g in positions[1:]:
        assert L == positions[0][0] and np.array_equal(g, positions[0][1])
    fresh, _ = make_sim()
    again = run(fresh, c)
    assert again[0] == first[0]
    for a, b in zip(again[1:], first[1:]):
        assert np.array_equal(a, b)


def test_fault_names_the_lowest_faulty_particle(sim):
    """NaN in F of particles N/2 - 1 (the last of lane 0's share), N/2 (the first of lane 1's) and N - 1 at
    step 0: whichever lane reaches its faulty particle first, the report names particle N/2 - 1."""
    sim, x0 = sim
    F = np.tile(np.eye(2), (N, 1, 1))
    for p in (N // 2 - 1, N // 2, N - 1):
        F[p, 1, 1] = np.nan
    write_step(sim.fields, 0, x0, np.zeros((N, 2)), np.zeros((N, 2, 2)), F)
    try:
        for _ in range(3):
            with pytest.raises(mls_mpm.SimulationError, match=rf"^step 0: particle {N // 2 - 1} has a non-finite"):
                sim.forward(sim.zero_controls())
    finally:
        sim.set_initial(x0)
