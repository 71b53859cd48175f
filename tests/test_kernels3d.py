"""The 3D twins of the reverse-kernel tests: each hand-written reverse kernel against central differences of its
forward kernel, in float64, on a 12^3 grid (thesis eq 41-71).

The Tape checks of the same kernels in 3D are in tests/test_tape3d.py (in a Taichi runtime initialised for the 3D
Tape); this module checks them against a second, independent oracle, the directional derivative: for the random linear
functional L = sum_y w . y of the kernel's outputs y, <dL/dz, d> from the reverse kernel against
(L(z + eps d) - L(z - eps d)) / (2 eps) along a random unit direction d of its inputs z, eps = 1e-6. L is smooth in z
there (no particle crosses a cell boundary within eps), so the difference is exact to its truncation O(eps^2) and its
cancellation, 64 ulps of |L| over eps (as `mls-mpm check` states it): each check passes at rel err <= 1e-6 or an
absolute error below that floor (observed: rel err 1e-10 to 2e-6, the larger ones where <dL/dz, d> is 1e-5 of |L| and
the floor decides). A direction is drawn per input set, so each input's adjoint is tested alone and then all together.
"""
import numpy as np
import pytest

from adjoint.losses import grid_loss_reverse, splat_reverse
from adjoint.transfer import g2p_reverse, p2g_reverse
from conftest import rel_err
from mls_mpm import losses
from mls_mpm.transfer import g2p, p2g
from test_adjoint_kernels import CONTROL_STEP, PLAIN_STEP, Pair, kernel_config, loss_specs, put_grid_adjoint

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

EPS = 1e-6
TOL = 1e-6
ROUND_OFF = 64 * float(np.finfo(np.float64).eps)  # the relative round-off of a float64 loss: 64 ulps


def agree(analytic, fd, L):
    """Relative error within TOL, or an absolute error below the finite difference's cancellation floor."""
    return rel_err(analytic, fd) <= TOL or abs(analytic - fd) <= ROUND_OFF * abs(L) / EPS


@pytest.fixture(scope="module")
def pair3():
    """A 3D Pair with mass and colour loss grids (8^3 and 4^3, a penalty grid) and a position target."""
    rng = np.random.default_rng(23)
    grids, colors = loss_specs(rng, 3)
    pair = Pair(kernel_config(3), loss_grids=grids, colors=True)
    for g, spec in zip(pair.s.loss_grids, grids):
        g.target.from_numpy(spec.target)
        if spec.alpha is not None:
            g.alpha.from_numpy(spec.alpha)
    pair.s.color.from_numpy(colors)
    return pair


def randomize_inside(pair, rng):
    """Random inputs with every particle's stencil on the grid and at least EPS * 1e3 from a cell boundary, so
    that the central differences see no change of base node (the kernels' only non-smooth point)."""
    pair.randomize(rng)
    x = pair.s.x.to_numpy()
    n = pair.n
    cells = rng.integers(2, n - 3, x.shape)
    x[:] = (cells + rng.uniform(0.01, 0.99, x.shape)) / n
    pair.s.x.from_numpy(x)
    return x


def directional(adjoints, d):
    return sum(float(np.sum(adjoints[k] * d[k])) for k in d)


def assert_matches_central_difference(s, L, adj, z0, inputs, f, rng):
    """<adj, d> against (L(z + eps d) - L(z - eps d)) / (2 eps) along a random unit direction d of the fields
    `inputs` at step f (z0: their values, restored afterwards)."""
    d = unit(rng, {k: z0[k][f].shape for k in inputs})

    def at(sign):
        for k in inputs:
            z = z0[k].copy()
            z[f] += sign * EPS * d[k]
            getattr(s, k).from_numpy(z)
        return L()

    plus, minus = at(1.0), at(-1.0)
    for k in inputs:
        getattr(s, k).from_numpy(z0[k])
    assert agree(directional(adj, d), (plus - minus) / (2 * EPS), max(abs(plus), abs(minus)))


def unit(rng, shapes):
    d = {k: rng.standard_normal(shape) for k, shape in shapes.items()}
    norm = np.sqrt(sum(np.sum(v * v) for v in d.values()))
    return {k: v / norm for k, v in d.items()}


@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("inputs", [("x",), ("F",), ("grid_v",), ("x", "F", "grid_v")])
def test_g2p_reverse_matches_central_differences(pair3, f, inputs):
    """g2p_reverse (g2p_particle_reverse, g2p_slab_reverse; eq 47-48, 57 first term, 66-69) in 3D: the adjoints
    of x^f, F^f and v_i^f for L = sum w . (x, v, C, F)^{f+1}, against central differences of g2p (eq 18-21)."""
    pair, s, a = pair3, pair3.s, pair3.a
    rng = np.random.default_rng(500 + f + 10 * len(inputs))
    randomize_inside(pair, rng)
    w = pair.upstream.draw(rng, ["x", "v", "C", "F"])

    def L():
        g2p(s, f)
        return sum(float(np.sum(w.np[k] * getattr(s, k).to_numpy()[f + 1])) for k in ("x", "v", "C", "F"))

    g2p(s, f)
    src, dst = (f + 1) % 2, f % 2
    a.adj_grid_v.fill(0.0)
    for k in ("x", "v", "C", "F"):
        up = np.zeros((2,) + w.np[k].shape)
        up[src] = w.np[k]
        getattr(a, "adj_" + k).from_numpy(up)
    g2p_reverse(s, a, f)
    adj = {"x": a.adj_x.to_numpy()[dst], "F": a.adj_F.to_numpy()[dst], "grid_v": a.adj_grid_v.to_numpy()}
    z0 = {"x": s.x.to_numpy(), "F": s.F.to_numpy(), "grid_v": s.grid_v.to_numpy()}
    assert_matches_central_difference(s, L, adj, z0, inputs, f, rng)


@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("inputs", [("x",), ("v",), ("C",), ("F",), ("x", "v", "C", "F")])
def test_p2g_reverse_matches_central_differences(pair3, f, inputs):
    """p2g_reverse (p2g_particle_reverse, p2g_slab_reverse, the 3D stress_reverse; eq 54-65, 71) in 3D: the
    adjoints of x, v, C, F of step f for L = sum_i w_m m_i + w_p . p_i of grid f, against central differences of
    p2g (eq 14-16 with drag and F + F_pc at a control step)."""
    pair, s, a = pair3, pair3.s, pair3.a
    rng = np.random.default_rng(600 + f + 10 * len(inputs))
    randomize_inside(pair, rng)
    w = pair.upstream.draw(rng, ["m", "p"])

    def L():
        s.grid_mp.fill(0.0)
        p2g(s, f)
        return float(np.sum(w.np["m"] * s.grid_mass()[f]) + np.sum(w.np["p"] * s.grid_momentum()[f]))

    put_grid_adjoint(a, w.np["m"], w.np["p"])
    for k in ("x", "v", "C", "F"):
        getattr(a, "adj_" + k).fill(0.0)
    a.adj_F_pc.fill(0.0)
    p2g_reverse(s, a, f)
    dst = f % 2
    adj = {k: getattr(a, "adj_" + k).to_numpy()[dst] for k in ("x", "v", "C", "F")}
    if f % pair.cfg.stride == 0:  # eq 55: the control's adjoint is dL/d(F + F_pc)
        assert np.array_equal(a.adj_F_pc.to_numpy()[f // pair.cfg.stride], adj["F"])
    z0 = {k: getattr(s, k).to_numpy() for k in ("x", "v", "C", "F")}
    assert_matches_central_difference(s, L, adj, z0, inputs, f, rng)


@pytest.mark.parametrize("gi", range(4), ids=["mass fine alpha", "mass coarse", "log mass fine alpha", "color fine"])
def test_loss_seed_matches_central_differences(pair3, gi):
    """grid_loss_reverse and splat_reverse (eq 41-43, 72) on 3D loss grids (8^3, 4^3; particles near the domain's
    edges drop nodes beyond it): dL/dx_p^f against central differences of splat + grid_loss."""
    pair, s, a = pair3, pair3.s, pair3.a
    f = 3
    rng = np.random.default_rng(700 + gi)
    x = randomize_inside(pair, rng)
    g = s.loss_grids[gi]

    def L():
        s.loss[None] = 0.0
        g.m.fill(0.0)
        losses.splat(s, g, f)
        losses.grid_loss(s, g)
        return s.loss[None]

    L()
    a.adj_x.fill(0.0)
    grid_loss_reverse(s, g)
    splat_reverse(s, g, a, f)
    assert_matches_central_difference(s, L, {"x": a.adj_x.to_numpy()[f % 2]}, {"x": x}, ("x",), f, rng)
