"""The debiased Sinkhorn divergence on mass grids (mls_mpm/ot.py): against an exact transport solver (POT's
ot.emd2) within the entropic bias derived in the module docstring, its gradient against central finite
differences in float64, zero for coinciding grids, and finite where nodes are empty or masses differ by 10^6."""
import numpy as np
import pytest

from mls_mpm.ot import sinkhorn_divergence, softmin

ot = pytest.importorskip("ot", reason="POT (pip install pot, in the test extra) is the exact-OT oracle")

TOL = 1e-12  # Sinkhorn stopping tolerance of these tests (potential change per iteration, relative to eps)


def entropy(p):
    p = p[p > 0]
    return float(-np.sum(p * np.log(p)))


def nodes(res, dim):
    """Coordinates i h of every node, in C order, for the exact solver's cost matrix."""
    axes = np.meshgrid(*[np.arange(res)] * dim, indexing="ij")
    return np.stack(axes, -1).reshape(-1, dim) / res


def exact_cost(a, b):
    """min_P <P, |x - y|^2 / 2> over plans between a / |a| and b / |b| (network simplex, POT)."""
    x = nodes(a.shape[0], a.ndim)
    M = 0.5 * ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    return float(ot.emd2(a.ravel() / a.sum(), b.ravel() / b.sum(), M))


def random_pair(shape, seed):
    """Two blobs of random masses with disjoint supports, empty nodes elsewhere."""
    rng = np.random.default_rng(seed)
    a, b = np.zeros(shape), np.zeros(shape)
    res = shape[0]
    lo = tuple(slice(1, res // 3 + 1) for _ in shape)
    hi = tuple(slice(res // 2, res - 1) for _ in shape)
    a[lo] = rng.random(a[lo].shape) + 0.1
    b[hi] = rng.random(b[hi].shape) + 0.1
    return a, b


@pytest.mark.parametrize("shape, blur, seed", [((12, 12), 1 / 12, 0), ((12, 12), 0.5 / 12, 1), ((10, 10), 0.1, 2),
                                               ((24,), 1 / 24, 3), ((6, 6, 6), 1 / 6, 4)])
def test_balanced_divergence_within_the_entropic_bias_of_exact_transport(shape, blur, seed):
    """|S - OT_0| <= eps (H(a) + H(b)) / 2 for probability grids (module docstring), eps = blur^2."""
    a, b = random_pair(shape, seed)
    r = sinkhorn_divergence(a, b, blur, tol=TOL)
    exact = exact_cost(a, b)
    bias = blur ** 2 * (entropy(a.ravel() / a.sum()) + entropy(b.ravel() / b.sum())) / 2
    assert r.change <= TOL
    assert abs(r.value - exact) <= bias + 1e-10, (r.value, exact, bias)
    assert abs(r.value - exact) <= 0.05 * exact  # and close in fact: a few percent at a blur of a cell or less


def test_translation_costs_exactly_half_the_squared_distance():
    """A blob moved by (3, 2) cells: the exact cost is |d|^2 / 2, and for a translation the debiased divergence
    has no entropic bias at all (the self-terms cancel it), at every blur."""
    res = 16
    a = np.zeros((res, res))
    a[3:7, 4:8] = np.arange(1, 17).reshape(4, 4)
    b = np.roll(np.roll(a, 3, axis=0), 2, axis=1)
    half_d2 = 0.5 * (3 ** 2 + 2 ** 2) / res ** 2
    assert rel(exact_cost(a, b), half_d2) <= 1e-12
    for blur in (2.0, 1.0, 0.7):
        assert rel(sinkhorn_divergence(a, b, blur / res, tol=TOL).value, half_d2) <= 1e-9


def fd(a, b, d, blur, reach=None, t=1e-6, tol=TOL):
    return (sinkhorn_divergence(a + t * d, b, blur, reach, tol=tol).value
            - sinkhorn_divergence(a - t * d, b, blur, reach, tol=tol).value) / (2 * t)


def rel(x, y):
    return abs(x - y) / max(abs(x), abs(y), 1e-300)


@pytest.mark.parametrize("reach", [None, 0.3])
def test_gradient_matches_central_differences(reach):
    """dS/da from the potentials (envelope theorem) against central differences along random directions,
    <= 1e-6 relative, with every node holding mass so that a - t d stays a measure."""
    a, b = random_pair((12, 12), 5)
    a += 0.02
    rng = np.random.default_rng(6)
    r = sinkhorn_divergence(a, b, 1 / 12, reach, tol=TOL)
    for _ in range(2):
        d = rng.standard_normal(a.shape)
        assert rel(float(np.sum(r.grad * d)), fd(a, b, d, 1 / 12, reach)) <= 1e-6


@pytest.mark.parametrize("reach", [None, 0.3])
def test_gradient_at_empty_nodes_is_the_one_sided_derivative(reach):
    """Where a has no mass, mass can only be added: dS/da_i there equals the second-order one-sided difference
    (-3 S(0) + 4 S(t) - S(2t)) / (2t) along a direction adding mass on the empty nodes next to a's support.

    Farther empty nodes have the same derivative at 0, but there S curves on a mass scale of R_i^2, R_i the
    blurred mass of a reaching node i (exp(-distance^2 / 2 eps)), far below any usable finite-difference step.
    """
    a, b = random_pair((12, 12), 7)
    support = a > 0
    near = np.zeros_like(support)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            near |= np.roll(np.roll(support, di, axis=0), dj, axis=1)
    d = np.where(near & ~support, np.random.default_rng(8).random(a.shape), 0.0)
    assert np.count_nonzero(d) >= 10
    r = sinkhorn_divergence(a, b, 1 / 12, reach, tol=TOL)
    assert np.all(np.isfinite(r.grad))
    t = 1e-8
    S = [sinkhorn_divergence(a + k * t * d, b, 1 / 12, reach, tol=TOL).value for k in (0, 1, 2)]
    assert rel(float(np.sum(r.grad * d)), (-3 * S[0] + 4 * S[1] - S[2]) / (2 * t)) <= 1e-5


@pytest.mark.parametrize("reach", [None, 0.3])
def test_zero_when_the_grids_coincide(reach):
    a, _ = random_pair((12, 12), 9)
    r = sinkhorn_divergence(a, a, 1 / 12, reach, tol=TOL)
    assert abs(r.value) <= 1e-14 * a.sum()
    assert np.max(np.abs(r.grad)) <= 1e-12
    if reach is None:  # the balanced divergence compares shapes: a scaled copy is the same shape
        assert abs(sinkhorn_divergence(a, 7.0 * a, 1 / 12, tol=TOL).value) <= 1e-14


def test_masses_differing_by_a_million_stay_finite_and_differentiable():
    """Unbalanced: a target a million times heavier. Value and gradient finite, gradient against FD."""
    a, b = random_pair((10, 10), 10)
    b *= 1e6
    a += 0.01
    r = sinkhorn_divergence(a, b, 0.1, reach=0.3, tol=1e-14)
    assert np.isfinite(r.value) and r.value > 0 and np.all(np.isfinite(r.grad))
    d = np.random.default_rng(11).standard_normal(a.shape)
    # S ~ 1e5 here: a larger step and a tighter Sinkhorn tolerance keep round-off below the comparison
    assert rel(float(np.sum(r.grad * d)), fd(a, b, d, 0.1, 0.3, t=1e-5, tol=1e-14)) <= 1e-6
    balanced = sinkhorn_divergence(a, b, 0.1, tol=TOL)  # normalised: the same as b at its own scale
    assert rel(balanced.value, sinkhorn_divergence(a, b / 1e6, 0.1, tol=TOL).value) <= 1e-12


def test_softmin_is_the_dense_log_sum_exp():
    """The separable blur equals the dense sum over all node pairs (a 5^3 grid: 125 x 125 pairs)."""
    rng = np.random.default_rng(13)
    h = rng.standard_normal((5, 5, 5))
    h[0, 0, :] = -np.inf  # empty nodes drop out
    x = nodes(5, 3)
    eps = 0.03
    C = 0.5 * ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    z = h.ravel()[None, :] - C / eps
    top = z.max(axis=1, keepdims=True)
    dense = -eps * (top[:, 0] + np.log(np.exp(z - top).sum(axis=1)))
    assert np.max(np.abs(softmin(h, eps).ravel() - dense)) <= 1e-12


@pytest.mark.parametrize("a, b, blur, reach, match", [
    (np.ones((4, 4)), np.ones((4, 5)), 0.1, None, "one shape"),
    (-np.ones((4, 4)), np.ones((4, 4)), 0.1, None, "non-negative"),
    (np.zeros((4, 4)), np.ones((4, 4)), 0.1, None, "some mass"),
    (np.ones((4, 4)), np.ones((4, 4)), 0.0, None, "blur"),
    (np.ones((4, 4)), np.ones((4, 4)), 0.1, -1.0, "reach"),
])
def test_bad_input_is_refused(a, b, blur, reach, match):
    with pytest.raises(ValueError, match=match):
        sinkhorn_divergence(a, b, blur, reach)


@pytest.mark.parametrize("reach", [None, 0.3], ids=["balanced", "unbalanced"])
def test_over_relaxed_iteration_reaches_the_plain_one_in_fewer_iterations(reach):
    """The cross potentials' over-relaxed updates (relax = RELAX) and plain alternating Sinkhorn (relax = 1)
    converge to the same divergence and gradient (to 1e-10 relative at TOL), the over-relaxed one in fewer
    iterations here (a disk to an L: 85 against 159 balanced; on the morph suite's grids 41-121 against 47-295;
    plain alternating updates can also be the faster, e.g. a disk splitting in two: 84 against 69); a relaxation
    near the edge of (0, 2) still converges to the same point."""
    n = 32  # a disk and an L of strokes 4 cells wide, at the blur morph uses (2 cells): a morph's loss grid
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = ((i - 16) ** 2 + (j - 16) ** 2 <= 36) * (7.0 if reach else 1.0)  # unbalanced: masses that differ
    b = np.zeros((n, n))
    b[8:24, 14:18] = b[20:24, 14:26] = 1.0
    plain = sinkhorn_divergence(a, b, 2 / n, reach, tol=TOL, relax=1.0)
    fast = sinkhorn_divergence(a, b, 2 / n, reach, tol=TOL)
    assert fast.change <= TOL and plain.change <= TOL
    assert fast.iterations < plain.iterations
    assert abs(fast.value - plain.value) <= 1e-10 * abs(plain.value)
    assert np.abs(fast.grad - plain.grad).max() <= 1e-8 * np.abs(plain.grad).max()
    wild = sinkhorn_divergence(a, b, 2 / n, reach, tol=TOL, relax=1.999)  # near the edge of (0, 2)
    assert wild.change <= TOL and abs(wild.value - plain.value) <= 1e-10 * abs(plain.value)


def test_over_relaxation_falls_back_when_it_does_not_halve_the_change(monkeypatch):
    """With a patience of 1 iteration no over-relaxed phase can halve its change in time: the fallback to plain
    alternating updates must take over and end at the plain iteration's result."""
    import mls_mpm.ot as mot

    a, b = random_pair((12, 12), 6)
    plain = sinkhorn_divergence(a, b, 1 / 12, tol=TOL, relax=1.0)
    monkeypatch.setattr(mot, "RELAX_PATIENCE", 1)
    r = sinkhorn_divergence(a, b, 1 / 12, tol=TOL, relax=1.999)
    assert r.change <= TOL and abs(r.value - plain.value) <= 1e-10 * abs(plain.value)


@pytest.mark.parametrize("relax", [0.0, 2.0, -1.0, float("nan")])
def test_relaxation_outside_its_interval_is_refused(relax):
    a, b = random_pair((8, 8), 7)
    with pytest.raises(ValueError, match=r"relax = .*: expected a number in \(0, 2\)"):
        sinkhorn_divergence(a, b, 1 / 8, relax=relax)
