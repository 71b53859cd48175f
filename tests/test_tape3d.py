"""The 3D twins of the reverse-kernel Tape tests (thesis eq 41-72): each hand-written reverse kernel with a stencil
loop against ti.ad.Tape on its forward twin, in float64 on a 12^3 grid, rel err <= 1e-8 (the checks themselves
are those of tests/test_adjoint_kernels.py, run on 3D inputs).

In 3D the stencil's first axis is a runtime loop, whose reverse Taichi 1.7.4 builds only with matrices scalarized
(mls_mpm.runtime.needs_scalarized), so this module initialises Taichi for the Tape (runtime.ensure(cfg, tape=True))
and gives the next module the plain float64 runtime back. Whole trajectories, manual against the Tape, are in
tests/test_gradients.py (there Simulator.gradient_tape runs the 3D Tape in a child process).
"""
import pytest

import mls_mpm
from mls_mpm import runtime
from test_adjoint_kernels import CONTROL_STEP, LOSS_GRIDS, PLAIN_STEP, Pair, kernel_config, make_loss_pair
from test_adjoint_kernels import test_g2p_reverse_matches_tape as g2p_check
from test_adjoint_kernels import test_grid_loss_seed_matches_tape as grid_loss_check
from test_adjoint_kernels import test_p2g_reverse_matches_tape as p2g_check
from test_adjoint_kernels import test_position_loss_seed_matches_tape as position_check
from test_adjoint_kernels import test_seed_sums_every_loss_and_zeroes_the_rest as seed_check

pytestmark = pytest.mark.usefixtures("taichi_tape_module")


@pytest.fixture(scope="module")
def taichi_tape_module():
    runtime.ensure(kernel_config(3), tape=True)
    assert runtime.RUNTIME.settings.scalarized
    yield
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"), tape=False)


@pytest.fixture(scope="module")
def pair3():
    return Pair(kernel_config(3))


@pytest.fixture(scope="module")
def loss_pair3():
    return make_loss_pair(3)


@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("which", ["x", "v", "C", "F", "x v C F"])
def test_g2p_reverse_matches_tape_3d(pair3, f, which):
    """g2p_reverse vs Tape on g2p in 3D (eq 47-48, 57, 66-69): rel err <= 1e-8 (test_adjoint_kernels' check)."""
    g2p_check(pair3, f, which)


@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("which", ["m", "p", "m p"])
def test_p2g_reverse_matches_tape_3d(pair3, f, which):
    """p2g_reverse vs Tape on p2g in 3D (eq 54-65, 71; the 3D stress and its closed-form reverse): rel err <= 1e-8."""
    p2g_check(pair3, f, which)


@pytest.mark.parametrize("gi", range(len(LOSS_GRIDS)), ids=LOSS_GRIDS)
def test_grid_loss_seed_matches_tape_3d(loss_pair3, gi):
    """grid_loss_reverse and splat_reverse vs Tape on splat + grid_loss on 3D loss grids (eq 11-13, 41-43, 72)."""
    grid_loss_check(loss_pair3, gi)


def test_position_loss_seed_matches_tape_3d(loss_pair3):
    """position_loss_reverse vs Tape in 3D (eq 10)."""
    position_check(loss_pair3)


def test_seed_sums_every_loss_and_zeroes_the_rest_3d(loss_pair3):
    """evaluate_reverse vs one Tape of the full 3D loss (eq 41-46, 10)."""
    seed_check(loss_pair3)
