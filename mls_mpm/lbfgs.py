"""L-BFGS (Nocedal & Wright, Numerical Optimization, 2nd ed.: Alg 7.4, 7.5) with a strong Wolfe line search
(Alg 3.5, 3.6), in numpy on flat vectors, so that its whole state can be saved and restored exactly.

The state between two iterations is the iterate x, its loss f and gradient g, and the curvature pairs
s = x_{k+1} - x_k, y = g_{k+1} - g_k of the last MEMORY iterations, oldest first. `iterate` maps one state to
the next with no other memory, so an optimizer that saves that state after every iteration and later restarts
from it continues exactly as if it had not stopped.

The loss is given as two callables: loss(x) -> float (math.inf where the trial cannot be evaluated, e.g. the
simulation left the grid) and grad() -> the gradient at the x of the last loss call, asked for at every trial
with a finite loss.
"""
import math

import numpy as np

MEMORY = 10  # m: curvature pairs kept (N&W 7.2 suggest 3 to 20; scipy's L-BFGS-B default is 10)
C1 = 1e-4  # sufficient decrease: f(x + a p) <= f + C1 a g.p (N&W 3.6a)
C2 = 0.9  # curvature: |g(x + a p).p| <= C2 |g.p| (N&W 3.7b; 0.9 for quasi-Newton directions)
MAX_TRIALS = 20  # loss evaluations per line search (scipy's maxls)
GROW = 2.0  # the bracketing phase multiplies the trial step by this while it is too short
XTOL = 0.1  # a zoom interval narrower than this fraction of its larger step ends the search (scipy's xtol)
SHRINK = 0.66  # a zoom interval must shrink below this fraction of its width two trials before, or is bisected
CURVATURE_EPS = 1e-10  # a pair is kept only if s.y > CURVATURE_EPS |s| |y|, which keeps H positive definite


def direction(g, S, Y):
    """Search direction p = -H g by the two-loop recursion (Alg 7.4) over the pairs (S[i], Y[i]), oldest first,
    with H_0 = (s.y / y.y) I of the newest pair (eq 7.20); p = -g without pairs."""
    q = np.array(g, dtype=np.float64)
    if len(S) == 0:
        return -q
    rho = [1.0 / float(np.dot(y, s)) for s, y in zip(S, Y)]
    alpha = [0.0] * len(S)
    for i in range(len(S) - 1, -1, -1):
        alpha[i] = rho[i] * float(np.dot(S[i], q))
        q -= alpha[i] * Y[i]
    r = q * (float(np.dot(S[-1], Y[-1])) / float(np.dot(Y[-1], Y[-1])))
    for i in range(len(S)):
        beta = rho[i] * float(np.dot(Y[i], r))
        r += (alpha[i] - beta) * S[i]
    return -r


class _Trial:
    """One line-search trial a: loss phi(a), and where known the gradient and phi'(a) = g.p."""

    def __init__(self, a, phi, g=None, p=None):
        self.a, self.phi, self.g = a, phi, g
        self.dphi = None if g is None else float(np.dot(g, p))


def line_search(loss, grad, x, f, g, p, a0):
    """A step a along p with the strong Wolfe conditions (Alg 3.5; zoom: Alg 3.6), as (a, f_new, g_new).

    Returns None when MAX_TRIALS evaluations find no step with sufficient decrease. When they find one but not
    the curvature condition, the best such step is returned (its pair is then kept only if s.y > 0 enough).
    """
    dphi0 = float(np.dot(g, p))
    evals = [0]

    def trial(a):
        """The loss at x + a p, with its gradient where it is finite (the zoom interpolates with both)."""
        evals[0] += 1
        phi = loss(x + a * p)
        if not math.isfinite(phi):
            return _Trial(a, math.inf)
        return _Trial(a, phi, np.asarray(grad(), dtype=np.float64).ravel(), p)

    def sufficient(a, phi):
        return phi <= f + C1 * a * dphi0

    def curvature(t):
        return abs(t.dphi) <= -C2 * dphi0

    def zoom(before, t, lo, hi):
        """lo satisfies sufficient decrease and has the lower loss; the interval between lo and hi holds a
        strong Wolfe step (Alg 3.6). `t` is the trial that made this interval, `before` the best step before it.
        The interval ends the search, with lo, once it is narrower than XTOL of the larger step (lo is as good
        as any step in it); one that has not shrunk below SHRINK of its width two trials before is bisected
        (More & Thuente's safeguards: interpolation can creep towards one end)."""
        width = abs(hi.a - lo.a)
        width_before = 2.0 * width
        while evals[0] < MAX_TRIALS:
            if abs(hi.a - lo.a) <= XTOL * max(lo.a, hi.a):
                break
            a = _next_step(before, t, lo, hi)
            if abs(hi.a - lo.a) >= SHRINK * width_before:
                a = lo.a + 0.5 * (hi.a - lo.a)
            width_before, width = width, abs(hi.a - lo.a)
            t = trial(a)
            before = lo
            if not sufficient(t.a, t.phi) or t.phi >= lo.phi:
                hi = t
                continue
            if curvature(t):
                return t
            if t.dphi * (hi.a - lo.a) >= 0:
                hi = lo
            lo = t
        return lo if lo.a > 0 else None

    prev = _Trial(0.0, f, g, p)
    a = a0
    while evals[0] < MAX_TRIALS:
        t = trial(a)
        if not sufficient(t.a, t.phi) or (prev.a > 0 and t.phi >= prev.phi):
            best = zoom(prev, t, prev, t)
            break
        if curvature(t):
            best = t
            break
        if t.dphi >= 0:
            best = zoom(prev, t, t, prev)
            break
        prev, a = t, GROW * a
    else:
        best = prev if prev.a > 0 else None
    if best is None:
        return None
    return best.a, best.phi, best.g


def _cubic_min(x, y):
    """The minimiser of the cubic through the values and slopes of trials x and y (eq 3.59, in the scaled form
    of More & Thuente that avoids overflow), or None where it has none."""
    theta = 3.0 * (x.phi - y.phi) / (y.a - x.a) + x.dphi + y.dphi
    scale = max(abs(theta), abs(x.dphi), abs(y.dphi))
    if not 0.0 < scale < math.inf:  # flat, or values too far apart to interpolate
        return None
    disc = (theta / scale) ** 2 - (x.dphi / scale) * (y.dphi / scale)
    if disc < 0.0:
        return None
    gamma = math.copysign(scale * math.sqrt(disc), y.a - x.a)
    den = (gamma - x.dphi) + gamma + y.dphi
    if den == 0.0:
        return None
    return x.a + ((gamma - x.dphi) + theta) / den * (y.a - x.a)


def _next_step(before, t, lo, hi):
    """The next zoom trial in (lo, hi), chosen as More & Thuente (1994) choose it (scipy's L-BFGS-B line search
    does too) from the last trial t and the best step `before` it: where t's loss is higher (case 1), the cubic
    minimiser, or halfway from it to the quadratic one when that lies nearer `before`; where t is lower and the
    slopes differ in sign (case 2), the cubic or the secant step, whichever is farther from t; where t is lower
    with a smaller slope of the same sign (case 3), the nearer of the two, at most SHRINK of the way to the far
    end; else (case 4) the cubic minimiser of t and the far end. Where slopes are missing (an infinite loss) or
    the step falls outside (lo, hi), the midpoint."""
    a = None
    far = hi if t is lo else lo
    if t.dphi is not None and before.dphi is not None and t.a != before.a:
        d = t.a - before.a
        if t.phi > before.phi:  # case 1
            a = _cubic_min(before, t)
            den = (before.phi - t.phi) / d + before.dphi
            if a is not None and den != 0.0:
                quad = before.a + (before.dphi / den) / 2.0 * d
                if abs(a - before.a) >= abs(quad - before.a):
                    a += (quad - a) / 2.0
        elif t.dphi * math.copysign(1.0, before.dphi) < 0:  # case 2
            a = _cubic_min(before, t)
            secant = t.a + t.dphi / (t.dphi - before.dphi) * (before.a - t.a)
            if a is None or abs(a - t.a) <= abs(secant - t.a):
                a = secant
        elif abs(t.dphi) < abs(before.dphi):  # case 3
            secant = t.a + t.dphi / (t.dphi - before.dphi) * (before.a - t.a)
            a = _cubic_min(before, t)
            if a is None or (a - t.a) * (before.a - t.a) > 0 or abs(a - t.a) >= abs(secant - t.a):
                a = secant  # (a cubic minimum on before's side of t is no extrapolation)
            limit = t.a + SHRINK * (far.a - t.a)
            a = min(a, limit) if far.a > t.a else max(a, limit)
        elif far.dphi is not None and math.isfinite(far.phi) and far.a != t.a:  # case 4
            a = _cubic_min(t, far)
    inner_lo, inner_hi = sorted((lo.a, hi.a))
    if a is None or not math.isfinite(a) or not inner_lo < a < inner_hi:
        a = lo.a + 0.5 * (hi.a - lo.a)
    return a


def iterate(loss, grad, x, f, g, S, Y):
    """One L-BFGS iteration from (x, f, g) with pairs S, Y (lists of vectors, oldest first, at most MEMORY).

    The direction is -H g (Alg 7.4); where it is no descent direction (g.p >= 0), or where no pair is kept,
    steepest descent -g with a first trial step of length 1 (scipy's L-BFGS-B does this on its first
    iteration), else a first trial a = 1 (N&W 7.2). A line search that fails along -H g is tried once more
    along -g with the memory cleared. Returns (x, f, g, S, Y) of the next iterate, or None when the line
    search finds no decrease along -g either, or at once when g = 0 (x is stationary).
    """
    if not np.any(g):
        return None
    S, Y = list(S), list(Y)
    p = direction(g, S, Y) if S else None
    if p is None or not float(np.dot(g, p)) < 0.0:
        S, Y, p = [], [], -np.asarray(g, dtype=np.float64)
    while True:
        a0 = 1.0 if S else 1.0 / float(np.linalg.norm(p))
        found = line_search(loss, grad, x, f, g, p, a0)
        if found is not None:
            break
        if not S:
            return None
        S, Y, p = [], [], -np.asarray(g, dtype=np.float64)
    a, f_new, g_new = found
    x_new = x + a * p
    s, y = x_new - x, g_new - g
    if float(np.dot(s, y)) > CURVATURE_EPS * float(np.linalg.norm(s)) * float(np.linalg.norm(y)):
        S.append(s)
        Y.append(y)
        del S[:-MEMORY], Y[:-MEMORY]
    return x_new, f_new, g_new, S, Y
