"""Taichi's autodiff (ti.ad.Tape) over the forward kernels: the test oracle, never the production path.

In 3D the Tape needs Taichi initialised with matrices scalarized (runtime.needs_scalarized), which production runs
are not; where the running Taichi is not, `tape_gradients_in_child` runs the Tape in a child process initialised
for it (re-initialising this one would free the caller's fields).
"""
import os
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import taichi as ti

from . import losses, runtime
from .grid import grid_op
from .losses import OT_KINDS, ColorLoss, PositionLoss
from .state import State, upload_loss, write_step
from .transfer import g2p, p2g


def tape_state(cfg, n_particles, losses):
    """A grad-enabled State for the Tapes of `losses` on one scene and body: their loss grids side by side, the
    target positions if one of them is a PositionLoss, the particle colours if one is a ColorLoss.

    Taichi compiles a kernel once per State it is given, so one State serves the Tapes of several losses with one
    compile of p2g, grid_op, g2p and their reverse (about a minute in 3D); each loss adds only its loss kernels.
    """
    losses = list(losses)
    t = State(cfg, n_particles, loss_grids=[spec for loss in losses for spec in loss.grids],
              position_loss=any(isinstance(loss, PositionLoss) for loss in losses),
              colors=any(isinstance(loss, ColorLoss) for loss in losses), needs_grad=True)
    t.tape_losses, t.tape_scene = losses, (cfg, n_particles)
    return t


def _grids_of(t, cfg, n_particles, loss):
    """The loss grids of `t` (a tape_state) that hold `loss`'s terms, on the scene and body `t` was made for."""
    if t.tape_scene != (cfg, n_particles):
        raise ValueError("tape_gradient: this state was made for another config or particle count (tape_state)")
    start = 0
    for other in t.tape_losses:
        if other is loss:
            return t.loss_grids[start:start + len(loss.grids)]
        start += len(other.grids)
    raise ValueError("tape_gradient: this state was made for other losses (tape_state)")


def tape_gradient(cfg, init, loss, controls, validation=False, state=None):
    """(loss, dL/dF_pc, grad state) through ti.ad.Tape over the forward kernels p2g, grid_op, g2p.

    init: the step-0 particle state {x, v, C, F}; state: a tape_state made for this loss (among others) to reuse,
    else one is made. The production path never calls this: it is the oracle of the tests, `mls-mpm check` and
    the benchmark. Initialises Taichi for the Tape where it is not (runtime.ensure(cfg, tape=True)), which frees
    the fields of simulators built under other settings: see tape_gradients_in_child.
    """
    runtime.ensure(cfg, tape=True)
    np_dtype = np.float64 if cfg.dtype == "f64" else np.float32
    t = state if state is not None else tape_state(cfg, len(init["x"]), [loss])
    grids = _grids_of(t, cfg, len(init["x"]), loss)
    upload_loss(t, loss, grids)
    write_step(t, 0, *(np.asarray(init[k]).astype(np_dtype) for k in ("x", "v", "C", "F")))
    t.F_pc.from_numpy(np.asarray(controls).astype(np_dtype))
    for field in (t.grid_mp, t.grid_v, t.loss, *(g.m for g in grids)):
        field.fill(0.0)
    T = cfg.steps
    ot_grids = [g for g in grids if g.kind in OT_KINDS]
    ot_value = 0.0
    if ot_grids:
        # the OT divergence is computed in numpy, outside the Tape: a first pass finds the final node masses and
        # its gradient dS/dm (the seed); the taped pass then differentiates the linear stand-in sum_i seed_i m_i,
        # whose derivative through the trajectory is the seed's, the chain rule the manual reverse pass applies
        for f in range(T):
            p2g(t, f)
            grid_op(t, f)
            g2p(t, f)
        for g in ot_grids:
            g.m.fill(0.0)
            losses.splat(t, g, T)
            ot_value += losses.ot_loss(t, g)
        for field in (t.grid_mp, t.grid_v, t.loss, *(g.m for g in grids)):
            field.fill(0.0)
    with ti.ad.Tape(loss=t.loss, validation=validation):
        for f in range(T):
            p2g(t, f)
            grid_op(t, f)
            g2p(t, f)
        for g in grids:
            losses.splat(t, g, T)
            if g.kind in OT_KINDS:
                losses.seed_loss(t, g)
            else:
                losses.grid_loss(t, g)
        if isinstance(loss, PositionLoss):
            losses.position_loss(t, T)
    surrogate = sum(float(np.sum(g.seed.to_numpy() * g.m.to_numpy())) for g in ot_grids)
    return t.loss[None] - surrogate + ot_value, t.F_pc.grad.to_numpy().astype(np.float64), t


def tape_gradients_in_child(jobs, validation=False):
    """[(loss, dL/dF_pc)] of tape_gradient for each job (cfg, init, loss, controls), computed in one child Python
    process that initialises Taichi for the Tape. The kernels compile there: about a minute in 3D for the jobs of one
    scene and body (their config and particle count), which share a tape_state, plus a few seconds a loss."""
    with tempfile.TemporaryDirectory(prefix="mls_mpm_tape_") as folder:
        src, dst = Path(folder) / "jobs.pkl", Path(folder) / "results.pkl"
        with open(src, "wb") as fh:
            pickle.dump((jobs, validation), fh)
        root = str(Path(__file__).resolve().parents[1])  # the folder holding this mls_mpm
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
        done = subprocess.run([sys.executable, "-m", "mls_mpm.tape", str(src), str(dst)], env=env,
                              capture_output=True, text=True)
        if done.returncode != 0 or not dst.exists():
            last = (done.stderr.strip().splitlines() or ["no output"])[-1]
            raise RuntimeError(f"ti.ad.Tape in a child process failed (exit {done.returncode}): {last}")
        with open(dst, "rb") as fh:
            return pickle.load(fh)


def _child(src, dst):
    with open(src, "rb") as fh:
        jobs, validation = pickle.load(fh)
    losses_of = {}  # the jobs of one scene and body share one tape_state (one compile of the trajectory's kernels)
    for cfg, init, loss, _ in jobs:
        losses_of.setdefault((cfg, len(init["x"])), []).append(loss)
    states, results = {}, []
    for cfg, init, loss, controls in jobs:
        runtime.ensure(cfg, tape=True)  # a job under other settings re-initialises Taichi, freeing earlier states
        key = (cfg, len(init["x"]), runtime.RUNTIME.generation)
        if key not in states:
            states[key] = tape_state(cfg, len(init["x"]), losses_of[key[:2]])
        L, grad, _ = tape_gradient(cfg, init, loss, controls, validation, states[key])
        results.append((float(L), grad))
    with open(dst, "wb") as fh:
        pickle.dump(results, fh)


if __name__ == "__main__":
    _child(*sys.argv[1:3])
