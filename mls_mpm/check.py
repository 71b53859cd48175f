"""`mls-mpm check`: the manual gradient of a reduced scene against ti.ad.Tape and central finite differences.

Each comparison passes when its symmetric relative error is within the tolerance, or when the absolute
difference is below the round-off floor of the loss L: a loss is known to ROUND_OFF |L| at best, so a
gradient difference below ROUND_OFF |L| (per unit of the controls), or a central difference below
ROUND_OFF |L| / EPS, cannot be told from round-off (a particle whose controls barely reach the loss has a
gradient of 1e-19 and a finite difference of exactly 0).

A 3D scene (sim.dim = 3) is checked the same way; its Tape runs in a child process initialised for it
(Simulator.gradient_tape: Taichi's autodiff of the 3D stencil loop needs matrices scalarized), which adds about a
minute of compiling.
"""
import copy
import dataclasses
import math

import numpy as np

from . import problem as problems
from .errors import UserError
from .losses import OT_KINDS, ColorLoss, PositionLoss

EPS = 1e-6  # central-difference step along each random direction
# With an optimal-transport term the directional derivatives are small beside the loss, so at 1e-6 the
# cancellation error (~1e-16 |L| / eps) reaches ~1e-5 of them; 1e-4 keeps it ~1e-7 and the truncation (~eps^2)
# below that (tests/test_gradients.py FD_EPS). Sinkhorn then runs to OT_TOL_CHECK, so that the value and its
# gradient agree to round-off.
EPS_OT = 1e-4
OT_TOL_CHECK = 1e-12
DIRECTIONS = 3  # random directions of the finite-difference check
ROUND_OFF = 64 * float(np.finfo(np.float64).eps)  # relative round-off of a float64 loss: 64 ulps
TINY = 1e-300


class CheckError(UserError):
    """An option of `check` is out of range; the message names it and what is expected."""


def rel_err(a, b):
    """Symmetric relative error |a - b| / max(|a|, |b|, tiny) (norms for arrays)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), np.linalg.norm(b), TINY))


@dataclasses.dataclass(frozen=True)
class Comparison:
    """Two gradients (or directional derivatives) compared: relative and absolute error, and the round-off
    floor below which an absolute error passes whatever the relative one."""

    rel: float
    abs: float
    floor: float

    @classmethod
    def of(cls, a, b, floor):
        a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
        return cls(rel_err(a, b), float(np.linalg.norm(a - b)), floor)

    def ok(self, tol) -> bool:
        return self.rel <= tol or self.abs <= self.floor

    def by_floor(self, tol) -> bool:
        """Passes only because the absolute error is below the round-off floor."""
        return self.rel > tol and self.abs <= self.floor


def check_options(steps, particles, tol_tape, tol_fd):
    """Refuse options `check` cannot use, naming the option."""
    for option, value in (("--steps", steps), ("--particles", particles)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise CheckError(f"check {option} {value}: expected an integer >= 1")
    for option, value in (("--tol-tape", tol_tape), ("--tol-fd", tol_fd)):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
            raise CheckError(f"check {option} {value}: expected a finite number > 0")


def reduced(scene, steps, particles):
    """The scene in float64 with few steps, a subsample of its particles and the loss restricted to them."""
    cfg = scene.sim.replace(dtype="f64", steps=steps, stride=max(1, min(scene.sim.stride, steps // 3)))
    prob = problems.build(dataclasses.replace(scene, sim=cfg))
    keep = np.linspace(0, len(prob.x0) - 1, min(particles, len(prob.x0))).astype(int)
    loss = prob.loss
    if isinstance(loss, PositionLoss):
        loss = PositionLoss(loss.target[keep])
    elif isinstance(loss, ColorLoss):
        loss = loss.restricted(keep)
    if any(g.kind in OT_KINDS for g in loss.grids):
        loss = copy.copy(loss)
        loss.grids = tuple(dataclasses.replace(g, tol=OT_TOL_CHECK) if g.kind in OT_KINDS else g for g in loss.grids)
    return cfg, prob.x0[keep], loss


def check_scene(scene, args, emit=print, seed=0):
    """Print relative errors; true when both are within tolerance (or below the round-off floor)."""
    check_options(args.steps, args.particles, args.tol_tape, args.tol_fd)
    from .simulator import Simulator, tape_refused

    cfg, x0, loss = reduced(scene, args.steps, args.particles)
    sim = Simulator(cfg, x0, loss=loss)
    why = tape_refused(cfg)  # before the passes compile: gradient_tape would refuse only after them
    if why:
        raise CheckError(f"check {scene.name}: {why}; run the check with --set sim.arch=cpu or cuda")
    rng = np.random.default_rng(seed)
    c = 0.02 * rng.standard_normal(sim.control_shape)
    L = sim.forward(c)
    g = sim.backward()
    g_tape = sim.gradient_tape(c)
    eps = EPS_OT if any(grid.kind in OT_KINDS for grid in loss.grids) else EPS
    fd = []
    for _ in range(DIRECTIONS):
        d = rng.standard_normal(c.shape)
        plus, minus = sim.forward(c + eps * d), sim.forward(c - eps * d)
        fd.append((float(np.sum(g * d)), (plus - minus) / (2 * eps), max(abs(L), abs(plus), abs(minus))))
    tape = Comparison.of(g, g_tape, ROUND_OFF * abs(L))
    diffs = [Comparison.of(gd, f, ROUND_OFF * size / eps) for gd, f, size in fd]
    worst = max(diffs, key=lambda e: (not e.ok(args.tol_fd), e.rel))
    ok = tape.ok(args.tol_tape) and all(e.ok(args.tol_fd) for e in diffs)
    emit(f"{scene.name} (reduced: {len(x0)} particles, {cfg.steps} steps, stride {cfg.stride}, f64"
         + (", 3D)" if cfg.dim == 3 else ")"))
    emit(f"  manual vs ti.ad.Tape:              relative error {tape.rel:.3e} (tolerance {args.tol_tape:g})"
         + _floor_note(tape, args.tol_tape))
    emit(f"  manual vs central differences ({DIRECTIONS}): relative error {worst.rel:.3e} (tolerance {args.tol_fd:g})"
         + _floor_note(worst, args.tol_fd))
    emit("  OK" if ok else "  FAILED: gradient outside tolerance")
    return ok


def _floor_note(e, tol):
    if e.by_floor(tol):
        return f"; absolute error {e.abs:.3e} below the round-off floor {e.floor:.3e}"
    return ""
