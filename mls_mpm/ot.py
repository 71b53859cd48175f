"""Entropic optimal transport between two mass grids: the debiased Sinkhorn divergence and its gradient.

The mass loss of eq 11 compares node masses one node at a time, so material farther than the cubic kernel's
reach from where the target has mass gets no gradient (thesis 8.1, 7.2). Optimal transport compares where the
mass is as a whole; thesis 5.4 and 9.2 name it as the remedy for this transport problem.

Both grids are measures on the nodes x_i = i h (h = 1 / res per axis) of a regular grid, of any dimension,
with the cost C(x, y) = |x - y|^2 / 2. The entropic transport cost with blur sigma (eps = sigma^2)

    OT(a, b) = min_P <P, C> + eps KL(P | a x b) [+ rho KL(P 1 | a) + rho KL(P^T 1 | b), unbalanced]

is computed in its dual form by the log-domain Sinkhorn iteration. Its Gibbs kernel exp(-C / eps) is
separable on a grid (Solomon et al. 2015, "Convolutional Wasserstein distances"), so one iteration is one 1D
log-sum-exp blur per axis: res^(dim + 1) work, not the (res^dim)^2 of the dense kernel. The blur starts at
the grid's diameter and shrinks geometrically to sigma (eps-scaling, one symmetric averaged update of all four
potentials per blur, as Feydy et al. 2019), then iterates at sigma until the potentials stop changing: the self
potentials f_aa, g_bb by their symmetric averaged update (a contraction: tens of iterations), the cross pair
f_ba, g_ab by alternating, over-relaxed updates g <- (1 - w) g + w T(g) with w = RELAX (Thibault, Chizat,
Dossal and Papadakis 2017, "Overrelaxed Sinkhorn-Knopp"): 7-15 times fewer iterations than the averaged update
at the same tolerance (four morph-suite pairs at 32^2 and 64^2, tol 1e-5: 41-146 against 286-2,261; the
same divergence to 1e-12 at tol 1e-12). Should the over-relaxed iteration not halve its change within
RELAX_PATIENCE iterations, it falls back to w = 1 (plain alternating Sinkhorn, which converges for any marginals).

The debiased divergence S(a, b) = OT(a, b) - OT(a, a) / 2 - OT(b, b) / 2 [+ eps (|a| - |b|)^2 / 2] is zero
for a = b, positive otherwise, and tends to the exact transport cost as sigma -> 0 (Feydy et al. 2019;
Sejourne et al. 2019 for the unbalanced form). With the potentials at convergence (envelope theorem):

    balanced (reach None), on a / |a| and b / |b|:  S = <a', f_ba - f_aa> + <b', g_ab - g_bb>,
        dS/da'_i = f_ba,i - f_aa,i, and dS/da_i = (F_i - <a', F>) / |a| with F = f_ba - f_aa, a' = a / |a|;
    unbalanced (rho = reach^2, masses kept):
        S = (rho + eps/2) (<a, exp(-f_aa/rho) - exp(-f_ba/rho)> + <b, exp(-g_bb/rho) - exp(-g_ab/rho)>),
        dS/da_i = (rho + eps) (exp(-f_aa,i/rho) - exp(-f_ba,i/rho)).

Bias: OT_0 <= OT(a, b) <= OT_0 + eps min(H(a), H(b)) for probability vectors (the plan's KL to a x b is at most
the smaller entropy H), and 0 <= OT(a, a) <= eps H(a), so the balanced divergence lies within
eps (H(a) + H(b)) / 2 of the exact transport cost OT_0 (tests/test_ot.py checks this against an exact solver).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SinkhornResult:
    """The divergence, its gradient with respect to the first grid's node masses, and how it was reached."""

    value: float  # S(a, b), in (domain units)^2 (per unit mass for the balanced divergence)
    grad: np.ndarray  # dS/da, the shape of a
    iterations: int  # Sinkhorn iterations, eps-scaling included
    change: float  # largest change of a potential in the last iteration, relative to eps


def _cost_1d(res: int, eps: float) -> np.ndarray:
    """C_ij / eps along one axis: ((i - j) h)^2 / (2 eps)."""
    d = (np.arange(res)[:, None] - np.arange(res)[None, :]) / res
    return 0.5 * d * d / eps


@functools.lru_cache(maxsize=256)
def _axis_kernel(res: int, eps: float) -> tuple:
    """(fast, matrix) for one axis of `res` nodes at blur eps: (True, exp(-C / eps)) where no entry underflows
    (see FAST_COST), else (False, C / eps). Cached: a Sinkhorn loop asks for the same few (res, eps) thousands of
    times, and on the small loss grids building them cost as much as the blur itself. Read-only."""
    cost = _cost_1d(res, eps)
    fast = bool(cost.max() <= FAST_COST)
    matrix = np.exp(-cost) if fast else cost
    matrix.setflags(write=False)
    return fast, matrix


def softmin(h: np.ndarray, eps: float) -> np.ndarray:
    """-eps log sum_j exp(h_j - C_ij / eps) for every node i, one 1D log-sum-exp per axis (the separable kernel).

    h holds log-weights plus potential / eps; entries of -inf (empty nodes) drop out. A node whose sum is empty
    (h all -inf) gets +inf.
    """
    out = h
    with np.errstate(divide="ignore"):  # log(0) = -inf for an empty sum
        for axis in range(h.ndim):
            fast, matrix = _axis_kernel(h.shape[axis], eps)
            if fast:
                out = _blur_lse(out, matrix, axis)
            else:
                moved = np.moveaxis(out, axis, -1)  # (..., j)
                out = np.moveaxis(_logsumexp(moved[..., None, :] - matrix), -1, axis)  # (..., i)
    return -eps * out


# The fast path: log sum_j exp(z_j) K_ij = M + log sum_j exp(z_j - M) K_ij with M the line's largest z, one
# matrix product per axis. It is exact to round-off while no kernel entry underflows: the sum is at least
# K_ij* > exp(-FAST_COST) (j* the line's largest entry), and a term that exp(z_j - M) drops (below e^-745) is
# then e^-170 of it or less. Blurs too small for that (a long grid at a blur below ~res/37 cells) take the dense
# log-sum-exp.
FAST_COST = 575.0


def _blur_lse(z: np.ndarray, kernel: np.ndarray, axis: int) -> np.ndarray:
    """log sum_j exp(z_j) kernel_ij along `axis` of z (C-ordered), for a symmetric kernel (lines of -inf give
    -inf). The product runs on z in its own memory order, as (before, j, after) stacks: no transposed copies."""
    top = z.max(axis=axis, keepdims=True)
    top[~np.isfinite(top)] = 0.0
    e = np.exp(z - top)
    if axis == z.ndim - 1:
        s = e @ kernel
    else:
        s = (kernel @ e.reshape(math.prod(z.shape[:axis]), z.shape[axis], -1)).reshape(z.shape)
    return np.log(s) + top


def _logsumexp(z: np.ndarray) -> np.ndarray:
    """log sum_j exp(z_ij) over the last axis, shifted by the row's largest entry (rows of -inf give -inf)."""
    top = z.max(axis=-1, keepdims=True)
    top[~np.isfinite(top)] = 0.0
    return np.log(np.exp(z - top).sum(axis=-1)) + top[..., 0]


def _log(a: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.log(a)


def _epsilons(res: int, dim: int, blur: float, scaling: float) -> list:
    """eps-scaling: eps from the grid's squared diameter down to blur^2 by factors scaling^2."""
    diameter = math.sqrt(dim) * (res - 1) / res
    eps, out = diameter ** 2, []
    while eps > blur ** 2:
        out.append(eps)
        eps *= scaling ** 2
    out.append(blur ** 2)
    return out


RELAX = 1.5  # over-relaxation of the cross potentials' updates at the final blur (1: plain alternating Sinkhorn)
RELAX_PATIENCE = 100  # iterations within which the over-relaxed change must halve, else RELAX falls back to 1


def sinkhorn_divergence(a, b, blur: float, reach: float | None = None, scaling: float = 0.7, tol: float = 1e-9,
                        max_iterations: int = 10000, relax: float = RELAX) -> SinkhornResult:
    """S(a, b) and dS/da for two non-negative mass grids of the same shape (res,) * dim.

    blur: sigma = sqrt(eps) in domain units (the grid spans [0, 1) per axis); reach: None for the balanced
    divergence of a / |a| and b / |b|, else the unbalanced one with rho = reach^2, on the masses themselves;
    tol: stop when no potential changes by more than tol * eps in an iteration at the final blur (for each of
    the two loops there, at most max_iterations); relax: the cross potentials' over-relaxation, in (0, 2).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape or a.ndim < 1 or len(set(a.shape)) != 1:
        raise ValueError(f"a, b: expected two grids of one shape (res,) * dim, got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and a.min() >= 0 and b.min() >= 0):
        raise ValueError("a, b: expected finite, non-negative masses")
    mass_a, mass_b = float(a.sum()), float(b.sum())
    if mass_a <= 0 or mass_b <= 0:
        raise ValueError(f"a, b: expected some mass in both grids, got total masses {mass_a:g} and {mass_b:g}")
    if not blur > 0 or (reach is not None and not reach > 0):
        raise ValueError(f"blur = {blur!r}, reach = {reach!r}: expected numbers > 0 (reach: or None)")
    if not 0.0 < relax < 2.0:
        raise ValueError(f"relax = {relax!r}: expected a number in (0, 2) (1: plain alternating updates)")
    balanced = reach is None
    if balanced:
        a, b = a / mass_a, b / mass_b
    rho = math.inf if balanced else reach ** 2
    log_a, log_b = _log(a), _log(b)
    res, dim = a.shape[0], a.ndim
    epsilons = _epsilons(res, dim, blur, scaling)

    def damp(eps):  # the proximal step of the KL marginal penalty: 1 / (1 + eps / rho), 1 when balanced
        return 1.0 if balanced else 1.0 / (1.0 + eps / rho)

    eps = epsilons[0]
    lam = damp(eps)
    f_ba, g_ab = lam * softmin(log_b, eps), lam * softmin(log_a, eps)
    f_aa, g_bb = g_ab.copy(), f_ba.copy()
    iterations = 0
    has_a, has_b = a > 0, b > 0  # the nodes whose potentials enter the value

    def soft(log_w, potential, eps):
        return damp(eps) * softmin(log_w + potential / eps, eps)

    for eps in epsilons:  # eps-scaling: one symmetric averaged update of all four potentials per blur
        new = (soft(log_b, g_ab, eps), soft(log_a, f_ba, eps), soft(log_a, f_aa, eps), soft(log_b, g_bb, eps))
        f_ba, g_ab, f_aa, g_bb = (0.5 * (o + n) for o, n in zip((f_ba, g_ab, f_aa, g_bb), new))
        iterations += 1
    change_self = change = math.inf
    for _ in range(max_iterations):  # the self potentials, each its own symmetric averaged fixed point
        if change_self <= tol:
            break
        new_aa, new_bb = 0.5 * (f_aa + soft(log_a, f_aa, eps)), 0.5 * (g_bb + soft(log_b, g_bb, eps))
        change_self = max(_largest_change(f_aa, new_aa, has_a), _largest_change(g_bb, new_bb, has_b)) / eps
        f_aa, g_bb = new_aa, new_bb
        iterations += 1
    w, checkpoint = relax, math.inf
    for k in range(max_iterations):  # the cross pair: alternating updates, over-relaxed by w
        if change <= tol:
            break
        if k % RELAX_PATIENCE == 0:
            if change > 0.5 * checkpoint:
                w = 1.0  # not halving: plain alternating updates from here on
            checkpoint = change
        new_ba = (1.0 - w) * f_ba + w * soft(log_b, g_ab, eps)
        new_ab = (1.0 - w) * g_ab + w * soft(log_a, new_ba, eps)
        change = max(_largest_change(f_ba, new_ba, has_a), _largest_change(g_ab, new_ab, has_b)) / eps
        f_ba, g_ab = new_ba, new_ab
        iterations += 1
    change = max(change, change_self)
    # final extrapolation at the last blur (not averaged), as in Feydy et al.
    f_ba, g_ab, f_aa, g_bb = (soft(log_b, g_ab, eps), soft(log_a, f_ba, eps), soft(log_a, f_aa, eps),
                              soft(log_b, g_bb, eps))
    if balanced:
        value = float(np.sum(a * (f_ba - f_aa)) + np.sum(b * (g_ab - g_bb)))
        F = f_ba - f_aa
        grad = (F - np.sum(a * F)) / mass_a  # through the normalisation a' = a / |a|
    else:
        e_aa, e_ba = np.exp(-f_aa / rho), np.exp(-f_ba / rho)
        e_bb, e_ab = np.exp(-g_bb / rho), np.exp(-g_ab / rho)
        value = float((rho + 0.5 * eps) * (np.sum(a * (e_aa - e_ba)) + np.sum(b * (e_bb - e_ab))))
        grad = (rho + eps) * (e_aa - e_ba)
    return SinkhornResult(value, grad, iterations, float(change))


def _largest_change(old, new, mask):
    """Largest |new - old| over the nodes of mask, those with mass (potentials on empty nodes do not enter the
    value)."""
    return float(np.max(np.abs(new[mask] - old[mask]), initial=0.0))
