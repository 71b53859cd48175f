"""L-BFGS (mls_mpm/lbfgs.py) on plain numpy functions, without Taichi: the two-loop recursion is the inverse-BFGS
matrix applied to g, the line search ends at a strong Wolfe step, iterations converge on Rosenbrock's function,
an infinite loss makes the line search backtrack (asking no gradient there), and iterating from a saved state repeats a run bit for bit.
"""
import math

import numpy as np
import pytest

from mls_mpm import lbfgs
from mls_mpm.lbfgs import C1, C2, MEMORY, direction, iterate, line_search


class Function:
    """f(x) and its gradient with the loss(x) / grad() interface of lbfgs (grad: at the last loss call)."""

    def __init__(self, f, df, inf_beyond=None):
        self.f, self.df, self.inf_beyond = f, df, inf_beyond
        self.x, self.grads, self.losses = None, 0, 0

    def loss(self, x):
        self.x, self.losses = np.array(x), self.losses + 1
        if self.inf_beyond is not None and np.linalg.norm(x) > self.inf_beyond:
            return math.inf
        return float(self.f(x))

    def grad(self):
        self.grads += 1
        return self.df(self.x)


def rosenbrock(n=6):
    def f(x):
        return np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2)

    def df(x):
        g = np.zeros_like(x)
        g[:-1] = -400.0 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2.0 * (1.0 - x[:-1])
        g[1:] += 200.0 * (x[1:] - x[:-1] ** 2)
        return g

    return Function(f, df)


def run(fun, x, iterations, state=None):
    """(x, f, g, S, Y) after `iterations` iterations from x (or from a state), and the states after each."""
    if state is None:
        f = fun.loss(x)
        state = (x, f, fun.grad(), [], [])
    states = [state]
    for _ in range(iterations):
        nxt = iterate(fun.loss, fun.grad, *state)
        if nxt is None:
            break
        state = nxt
        states.append(state)
    return states


def test_direction_is_minus_the_inverse_bfgs_matrix_times_g():
    """The two-loop recursion equals H g with H built by the BFGS update (eq 6.17) from H_0 = (s.y / y.y) I of
    the newest pair (eq 7.20), applied to the pairs oldest first."""
    rng = np.random.default_rng(3)
    n = 5
    A = rng.standard_normal((n, n))
    A = A @ A.T + n * np.eye(n)  # a positive definite Hessian: y = A s, so s.y > 0
    S = [rng.standard_normal(n) for _ in range(4)]
    Y = [A @ s for s in S]
    g = rng.standard_normal(n)
    H = float(S[-1] @ Y[-1]) / float(Y[-1] @ Y[-1]) * np.eye(n)
    for s, y in zip(S, Y):
        rho = 1.0 / float(y @ s)
        V = np.eye(n) - rho * np.outer(y, s)
        H = V.T @ H @ V + rho * np.outer(s, s)
    assert np.allclose(direction(g, S, Y), -H @ g, rtol=1e-12, atol=1e-14)
    assert np.array_equal(direction(g, [], []), -g)


@pytest.mark.parametrize("a0", [1e-4, 1.0, 50.0])
def test_line_search_ends_at_a_strong_wolfe_step(a0):
    """From too short, about right and far too long first trials (the bracketing phase grows, the zoom
    shrinks), the step found satisfies both strong Wolfe conditions, and its loss and gradient are returned."""
    fun = rosenbrock()
    x = np.full(6, -0.5)
    f, g = fun.loss(x), fun.grad()
    p = -g / np.linalg.norm(g)
    a, f_new, g_new = line_search(fun.loss, fun.grad, x, f, g, p, a0)
    assert f_new == fun.f(x + a * p) and np.array_equal(g_new, fun.df(x + a * p))
    assert f_new <= f + C1 * a * float(g @ p)
    assert abs(float(g_new @ p)) <= C2 * abs(float(g @ p))


def test_line_search_backtracks_from_an_infinite_loss():
    """A trial the loss cannot evaluate (inf, like a simulation that left the grid) counts as too long."""
    fun = rosenbrock()
    fun.inf_beyond = 3.0
    x = np.full(6, -0.5)
    f, g = fun.loss(x), fun.grad()
    p = -g / np.linalg.norm(g)
    a, f_new, _ = line_search(fun.loss, fun.grad, x, f, g, p, 1e6)
    assert np.linalg.norm(x + a * p) <= 3.0 and f_new < f


def test_no_gradient_is_asked_for_at_an_infinite_loss():
    """A trial that cannot be evaluated (a simulation that left the grid) has no reverse pass to ask for."""
    fun = rosenbrock()
    fun.inf_beyond = 3.0
    real = fun.grad

    def grad():
        assert math.isfinite(fun.loss(fun.x)), "gradient asked for at an infinite loss"
        return real()

    x = np.full(6, -0.5)
    f, g = fun.loss(x), fun.grad()
    fun.losses = 0
    line_search(fun.loss, grad, x, f, g, -g / np.linalg.norm(g), 1e6)
    assert fun.losses > 2


def test_line_search_fails_along_an_ascent_direction():
    fun = rosenbrock()
    x = np.full(6, -0.5)
    f, g = fun.loss(x), fun.grad()
    fun.losses = 0
    assert line_search(fun.loss, fun.grad, x, f, g, g, 1.0) is None
    assert fun.losses == lbfgs.MAX_TRIALS


def test_iterations_converge_on_rosenbrock_and_keep_at_most_memory_pairs():
    fun = rosenbrock()
    states = run(fun, np.full(6, -1.0), 200)
    x, f, g, S, Y = states[-1]
    assert f < 1e-12 and np.allclose(x, 1.0, atol=1e-5), (len(states), f)
    assert len(states) < 150  # steepest descent takes thousands of iterations here
    assert max(len(s[3]) for s in states) == MEMORY
    losses = [s[1] for s in states]
    assert all(b < a for a, b in zip(losses, losses[1:]))  # sufficient decrease every iteration


def test_a_saved_state_continues_bit_for_bit():
    """Iterating from the state saved after iteration 7 (copies, as a checkpoint file holds) gives exactly the
    iterates of the uninterrupted run."""
    whole = run(rosenbrock(), np.full(6, -1.0), 20)
    x, f, g, S, Y = whole[7]
    saved = (x.copy(), float(f), g.copy(), [s.copy() for s in S], [y.copy() for y in Y])
    resumed = run(rosenbrock(), None, 13, state=saved)
    assert len(resumed) == 14 and len(whole) == 21
    for a, b in zip(resumed, whole[7:]):
        assert np.array_equal(a[0], b[0]) and a[1] == b[1] and np.array_equal(a[2], b[2])
        assert len(a[3]) == len(b[3]) and all(np.array_equal(u, v) for u, v in zip(a[3] + a[4], b[3] + b[4]))


def test_non_descent_direction_restarts_from_steepest_descent():
    """Pairs whose H sends -H g uphill (built for another function) are dropped: the step is along -g."""
    fun = rosenbrock()
    x = np.full(6, -0.5)
    f, g = fun.loss(x), fun.grad()
    S, Y = [g.copy()], [-g.copy()]  # s.y < 0: an H that maps g to +g
    assert float(g @ direction(g, S, Y)) > 0
    x_new, f_new, g_new, S_new, _ = iterate(fun.loss, fun.grad, x, f, g, S, Y)
    step = x_new - x
    assert f_new < f and np.allclose(step / np.linalg.norm(step), -g / np.linalg.norm(g), atol=1e-12)
    assert len(S_new) == 1 and np.array_equal(S_new[0], step)


def test_a_line_search_without_a_curvature_step_in_reach_ends_early():
    """phi(a) = -a + exp(1e6 (a - 1)) meets the curvature condition only where a is within ~1e-5 of 0.99999:
    the zoom stops once its interval is narrower than XTOL of the step, with the best sufficient-decrease step,
    instead of spending all MAX_TRIALS evaluations (a shipped scene lost iou that way)."""
    fun = Function(lambda x: -x[0] + math.exp(min(1e6 * (x[0] - 1.0), 700.0)),
                   lambda x: np.array([-1.0 + 1e6 * math.exp(min(1e6 * (x[0] - 1.0), 700.0))]))
    x = np.zeros(1)
    f, g = fun.loss(x), fun.grad()
    fun.losses = 0
    a, f_new, _ = line_search(fun.loss, fun.grad, x, f, g, np.ones(1), 3.0)
    assert fun.losses < lbfgs.MAX_TRIALS // 2, fun.losses
    assert 0.9 < a < 1.0 and f_new <= f + C1 * a * float(g[0])
