"""Losses on the final step: position (eq 10), mass (eq 11, 72), log mass, color (eq 12-13), optimal transport.

The loss classes hold user data (numpy); the kernels below evaluate them on a State.
A target array's shape sets its loss grid's resolution and dimension: (res, res) in 2D, (res, res, res) in 3D
(colour: one more axis of 3); entry [i, j] (3D: [i, j, k]) is the node at (i dx, j dx[, k dx]).
On a CPU the kernels' loops run serially (State.serial_losses): their float sums then have one order, so a
loss is bit-identical run after run; their work (one splat of the particles, one pass over each loss grid)
is small beside the steps'.
"""

import copy
from dataclasses import dataclass

import numpy as np
import taichi as ti

from . import ot
from .kernels import splat_particle
from .sizes import n_live
from .errors import UserError

OT_KINDS = ("ot", "color_ot")  # loss grids whose term ot_loss computes in numpy
OT_BLUR = 2.0  # default entropic blur sigma of the OT loss, in cells of each loss grid (see OTLoss)
COLOR_EMPTY = 1e-9  # a colour channel holding less than this fraction of a grid's colour-mass is left out of OT
OT_TOL = 1e-9  # Sinkhorn stops when no potential changes by more than this times eps in an iteration (1e-5 left
# the gradient of S(a, a), zero by definition, at ~1e-7 of a typical one; 1e-9 costs 1.6-2x the iterations of 1e-5)


class LossError(UserError):
    """A loss was given data of the wrong shape or value."""


@dataclass(frozen=True)
class GridSpec:
    kind: str
    res: int
    weight: float
    target: np.ndarray
    alpha: np.ndarray | None
    blur: float = 0.0  # OT grids: sigma in cells of this grid
    reach: float | None = None  # OT grids: None (balanced) or the unbalanced reach in domain units
    tol: float = OT_TOL  # OT grids: the Sinkhorn stopping tolerance

    @property
    def dim(self):
        """2 or 3: target holds (res,) * dim nodes of one or three channels."""
        return self.target.ndim - 1


class PositionLoss:
    """Eq 10: sum_p 1/2 |x_p - x_pu|^2 against per-particle target positions (N, dim)."""

    grids = ()

    def __init__(self, target_positions):
        self.target = _array(target_positions, "target_positions")
        if self.target.ndim != 2 or self.target.shape[1] not in (2, 3):
            raise LossError(f"target_positions: expected shape (N, 2) or (N, 3), got {self.target.shape}")

    @property
    def dim(self):
        return self.target.shape[1]

    def check(self, n_particles):
        if len(self.target) != n_particles:
            raise LossError(f"target_positions: {len(self.target)} rows, expected one per particle ({n_particles})")


class MassLoss:
    """Eq 11 / 72 on one or more loss grids (thesis 8.1): sum_g w_g sum_i 1/2 alpha_i (m_i - m_iu)^2.

    targets: list of (res, res) target mass grids ((res, res, res) in 3D); weights: one per grid (default 1);
    alpha: one per grid, a penalty array of the target's shape or None (alpha = 1); log: use the log mass loss
    1/2 (ln(m_i + 1) - ln(m_iu + 1))^2 per node instead of eq 11.
    """

    def __init__(self, targets, weights=None, alpha=None, log=False):
        self.grids = _grid_specs("log_mass" if log else "mass", targets, weights, alpha, channels=1)

    def check(self, n_particles):
        pass


class ColorLoss:
    """Eq 13 on loss grids: sum_g w_g sum_i 1/2 |c_i - c_iu|^2 with c_i = sum_p N m_p c_p (eq 12), plus, with
    ot_weights, optimal transport of each colour channel: sum_g ow_g sum_c S(c_g,c, c_gu,c), the debiased
    Sinkhorn divergence (balanced) of the channel's colour-mass, which pulls red material towards where the
    target is red however far it is (eq 13, like eq 11, reaches two cells). A channel empty in the body or the
    target of a grid is left out of its transport term.

    targets: list of (res, res, 3) target color-mass grids ((res, res, res, 3) in 3D); colors: (N, 3) particle RGB; weights: eq 13's, one
    per grid (0: none); ot_weights: the transport term's, one per grid (default none); blur, tol: as OTLoss.
    """

    def __init__(self, targets, colors, weights=None, ot_weights=None, blur=OT_BLUR, tol=OT_TOL):
        weights, ot_weights = _two_terms(targets, weights, ot_weights, "ot_weights", "a colour or a transport")
        if not (np.isfinite(blur) and blur > 0):
            raise LossError(f"blur: expected a number > 0 (cells), got {blur!r}")
        specs = _grid_specs("color", targets, [w or 1.0 for w in weights], None, channels=3)  # 0: checked above
        self.grids = tuple(GridSpec("color", g.res, w, g.target, None) for g, w in zip(specs, weights) if w > 0) + \
            tuple(GridSpec("color_ot", g.res, w, g.target, None, float(blur), None, float(tol))
                  for g, w in zip(specs, ot_weights) if w > 0)
        self.colors = _array(colors, "colors")
        if self.colors.ndim != 2 or self.colors.shape[1] != 3:
            raise LossError(f"colors: expected shape (N, 3), got {self.colors.shape}")

    def check(self, n_particles):
        if len(self.colors) != n_particles:
            raise LossError(f"colors: {len(self.colors)} rows, expected one per particle ({n_particles})")

    def restricted(self, keep):
        """The same loss (grids, weights, transport terms) for the particles `keep` only: their colours."""
        out = copy.copy(self)
        out.colors = self.colors[keep]
        return out


class OTLoss:
    """Optimal transport on loss grids (thesis 5.4, 9.2): sum_g w_g S(m_g, m_gu), the debiased Sinkhorn
    divergence of mls_mpm/ot.py between the body's node masses and the target's, plus, with mass_weights, the
    eq 11 mass loss on the same grids (sum_g mw_g sum_i 1/2 (m_i - m_iu)^2).

    Eq 11 pulls a node only towards its own target mass, so material beyond the cubic kernel's reach of the
    target gets no gradient (thesis 8.1); the transport cost pulls every node towards where the target's mass
    is. Its gradient dS/dm_i (the Sinkhorn potentials) seeds the reverse pass like dL/dm_i of eq 41.

    targets: list of (res, res) target mass grids ((res, res, res) in 3D); weights: one per grid (default 1); blur: sigma in cells of
    each grid (smaller: closer to the exact transport cost, more Sinkhorn iterations; below about res / 34
    cells the slower dense log-sum-exp is used); reach: None for the balanced divergence between the normalised
    grids (where the body ends up is compared, not how much mass it has), else the unbalanced divergence in which
    mass farther than about `reach` (domain units) is created or destroyed rather than moved; mass_weights: one
    per grid, 0 for none (a grid may carry either term or both: weights 0 drops its transport term); tol: the
    Sinkhorn stopping tolerance (OT_TOL: the value and the gradient are then exact to ~1e-10 relative, and the
    gradient of a body on its own masses is zero to that; the gradient tests use 1e-12).
    """

    def __init__(self, targets, weights=None, blur=OT_BLUR, reach=None, mass_weights=None, tol=OT_TOL):
        if not (np.isfinite(blur) and blur > 0):
            raise LossError(f"blur: expected a number > 0 (cells), got {blur!r}")
        if reach is not None and not (np.isfinite(reach) and reach > 0):
            raise LossError(f"reach: expected a number > 0 (domain units) or None, got {reach!r}")
        if not (np.isfinite(tol) and tol > 0):
            raise LossError(f"tol: expected a number > 0, got {tol!r}")
        weights, mass_weights = _two_terms(targets, weights, mass_weights, "mass_weights", "a transport or a mass")
        specs = _grid_specs("ot", targets, [w or 1.0 for w in weights], None, channels=1)  # 0: checked above
        for spec in specs:
            if not spec.target.sum() > 0:
                raise LossError(f"targets: the {spec.res}^{spec.dim} grid holds no mass; optimal transport needs some")
        transport = tuple(GridSpec("ot", g.res, w, g.target, None, float(blur), reach, float(tol))
                          for g, w in zip(specs, weights) if w > 0)
        mass = tuple(GridSpec("mass", g.res, float(w), g.target, None) for g, w in zip(specs, mass_weights) if w > 0)
        self.grids = transport + mass

    def check(self, n_particles):
        pass


def _array(a, name):
    a = np.asarray(a, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise LossError(f"{name}: holds NaN or Inf")
    return a


def _two_terms(targets, weights, others, name, what):
    """(weights, others) of a loss with two terms per grid: lists of numbers >= 0, one per target grid, with
    one term > 0 on every grid (weights default to 1, others to 0)."""
    weights = [1.0] * len(_list(targets)) if weights is None else list(weights)
    others = [0.0] * len(weights) if others is None else list(others)
    if len(others) != len(weights) or any(not (np.isfinite(w) and w >= 0) for w in weights + others):
        raise LossError(f"weights, {name}: expected one number >= 0 each per target grid ({len(weights)})")
    if any(w + o <= 0 for w, o in zip(weights, others)):
        raise LossError(f"weights, {name}: expected {what} weight > 0 on every grid")
    return weights, others


def _list(targets):
    return [targets] if isinstance(targets, np.ndarray) else list(targets)


def _grid_specs(kind, targets, weights, alpha, channels):
    targets = _list(targets)
    targets = [_array(t, "targets") for t in targets]
    if not targets:
        raise LossError("targets: expected at least one loss grid")
    weights = [1.0] * len(targets) if weights is None else list(weights)
    alpha = [None] * len(targets) if alpha is None else list(alpha)
    if len(weights) != len(targets) or len(alpha) != len(targets):
        raise LossError(f"weights/alpha: expected one per target grid ({len(targets)})")
    specs = []
    ch = ", 3" if channels == 3 else ""
    for t, w, a in zip(targets, weights, alpha):
        dim = t.ndim - (channels == 3)
        shape = (t.shape[0],) * dim + ((3,) if channels == 3 else ())
        if dim not in (2, 3) or t.shape != shape or t.shape[0] < 4:
            raise LossError(f"targets: expected square grids of shape (res, res{ch}) or cubic ones of shape "
                            f"(res, res, res{ch}) with res >= 4, got {t.shape}")
        if specs and dim != specs[0].dim:
            raise LossError(f"targets: grids of {specs[0].dim} and {dim} dimensions in one loss")
        if not (np.isfinite(w) and w > 0):
            raise LossError(f"weights: expected numbers > 0, got {w!r}")
        if a is not None:
            a = _array(a, "alpha")
            if a.shape != t.shape[:dim] or np.any(a < 0):
                raise LossError(f"alpha: expected a {t.shape[:dim]} array >= 0, got shape {a.shape}")
        specs.append(GridSpec(kind, t.shape[0], float(w), t.reshape(t.shape[:dim] + (channels,)), a))
    return tuple(specs)


@ti.func
def splat_value(s: ti.template(), g: ti.template(), p):
    """What particle p carries to a loss grid: m_p (eq 15) or m_p c_p (eq 12)."""
    value = ti.Vector.zero(float, g.channels)
    if ti.static(g.is_color):
        value = s.m_p * s.color[p]
    else:
        value[0] = s.m_p
    return value


@ti.kernel
def splat(s: ti.template(), g: ti.template(), f: ti.i32):
    """P2G of particle mass (or color-mass) of step f onto loss grid g, with g's own dx."""
    ti.loop_config(serialize=s.serial_losses)
    for p in range(n_live(s)):
        splat_particle(g.m, s.x[f, p], g.inv_dx, splat_value(s, g, p))  # nodes beyond the domain dropped


@ti.func
def node_residual(g: ti.template(), I):
    """m_i - m_iu (eq 41), or ln(m_i + 1) - ln(m_iu + 1) for the log mass loss."""
    r = g.m[I] - g.target[I]
    if ti.static(g.kind == "log_mass"):
        r = ti.log(g.m[I] + 1.0) - ti.log(g.target[I] + 1.0)
    return r


@ti.func
def node_penalty(g: ti.template(), I):
    """w_g alpha_i (eq 72; alpha_i = 1 without a penalty grid)."""
    a = g.weight
    if ti.static(g.has_alpha):
        a *= g.alpha[I]
    return a


@ti.kernel
def grid_loss(s: ti.template(), g: ti.template()):
    """L += w_g sum_i 1/2 alpha_i |r_i|^2 (eq 11, 13, 72)."""
    ti.loop_config(serialize=s.serial_losses)
    for I in ti.grouped(ti.ndrange(*g.shape)):  # a range, not a struct-for, which Taichi cannot serialize
        s.loss[None] += 0.5 * node_penalty(g, I) * node_residual(g, I).norm_sqr()


@ti.kernel
def position_loss(s: ti.template(), f: ti.i32):
    """L += sum_p 1/2 |x_p - x_pu|^2 (eq 10)."""
    ti.loop_config(serialize=s.serial_losses)
    for p in range(n_live(s)):
        s.loss[None] += 0.5 * (s.x[f, p] - s.target_x[p]).norm_sqr()


def ot_loss(s, g):
    """L += w_g S(m, m_u) on an OT grid (OTLoss), or w_g sum_c S(c_c, c_u,c) over the colour channels of a
    colour OT grid (ColorLoss ot_weights); writes w_g dS/dm_i into g.seed, which the reverse pass reads as
    dL/dm_i (adjoint.losses.ot_loss_reverse) and the Tape as the weights of its linear stand-in (seed_loss)."""
    m = g.m.to_numpy().astype(np.float64)  # (res,) * dim + (channels,)
    target = g.target_np.reshape(m.shape)
    seed, value = np.zeros_like(m), 0.0
    for c in range(m.shape[-1]):
        body, aim = m[..., c], target[..., c]
        if g.channels > 1 and not (body.sum() > COLOR_EMPTY * m.sum() and aim.sum() > COLOR_EMPTY * target.sum()):
            continue  # a colour channel that the body or the target lacks: nothing to transport
        r = ot.sinkhorn_divergence(body, aim, g.blur / g.res, g.reach, tol=g.tol)
        seed[..., c], value = g.weight * r.grad, value + g.weight * r.value
    g.seed.from_numpy(seed.astype(g.np_dtype))
    s.loss[None] += value
    return value


@ti.kernel
def seed_loss(s: ti.template(), g: ti.template()):
    """L += sum_i seed_i m_i: the Tape's linear stand-in for ot_loss, whose derivative is the same seed."""
    for I in ti.grouped(ti.ndrange(*g.shape)):
        s.loss[None] += g.seed[I].dot(g.m[I])


def evaluate(s, f):
    """Loss of step f: clear, splat and sum every active loss grid, then the position term."""
    s.loss[None] = 0.0
    for g in s.active_grids:
        g.m.fill(0.0)
        splat(s, g, f)
        if g.kind in OT_KINDS:
            ot_loss(s, g)
        else:
            grid_loss(s, g)
    if s.has_position_loss:
        position_loss(s, f)
    return s.loss[None]
