"""`mls-mpm check`: the manual gradient of a reduced scene against ti.ad.Tape and central finite differences."""
import dataclasses

import numpy as np

from . import problem as problems
from .losses import ColorLoss, PositionLoss
from .simulator import Simulator


def rel_err(a, b):
    """Symmetric relative error |a - b| / max(|a|, |b|, tiny) (norms for arrays)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), np.linalg.norm(b), 1e-300))


def reduced(scene, steps, particles):
    """The scene in float64 with few steps, a subsample of its particles and the loss restricted to them."""
    cfg = scene.sim.replace(dtype="f64", steps=steps, stride=max(1, min(scene.sim.stride, steps // 3)))
    prob = problems.build(dataclasses.replace(scene, sim=cfg))
    keep = np.linspace(0, len(prob.x0) - 1, min(particles, len(prob.x0))).astype(int)
    loss = prob.loss
    if isinstance(loss, PositionLoss):
        loss = PositionLoss(loss.target[keep])
    elif isinstance(loss, ColorLoss):
        loss = ColorLoss([g.target for g in loss.grids], loss.colors[keep], [g.weight for g in loss.grids])
    return cfg, prob.x0[keep], loss


def check_scene(scene, args, emit=print, seed=0):
    """Print relative errors; true when both are within tolerance."""
    cfg, x0, loss = reduced(scene, args.steps, args.particles)
    sim = Simulator(cfg, x0, loss=loss)
    rng = np.random.default_rng(seed)
    c = 0.02 * rng.standard_normal(sim.control_shape)
    sim.forward(c)
    g = sim.backward()
    g_tape = sim.gradient_tape(c)
    e_tape = rel_err(g, g_tape)
    e_fd = 0.0
    eps = 1e-6
    for _ in range(3):
        d = rng.standard_normal(c.shape)
        fd = (sim.forward(c + eps * d) - sim.forward(c - eps * d)) / (2 * eps)
        e_fd = max(e_fd, rel_err(float(np.sum(g * d)), fd))
    ok = e_tape <= args.tol_tape and e_fd <= args.tol_fd
    emit(f"{scene.name} (reduced: {len(x0)} particles, {cfg.steps} steps, stride {cfg.stride}, f64)")
    emit(f"  manual vs ti.ad.Tape:              relative error {e_tape:.3e} (tolerance {args.tol_tape:g})")
    emit(f"  manual vs central differences (3): relative error {e_fd:.3e} (tolerance {args.tol_fd:g})")
    emit("  OK" if ok else "  FAILED: gradient outside tolerance")
    return ok
