"""Taichi's autodiff (ti.ad.Tape) over the forward kernels: the test oracle, never the production path."""
import numpy as np
import taichi as ti

from . import losses, runtime
from .grid import grid_op
from .losses import OT_KINDS, ColorLoss, PositionLoss
from .state import State, upload_loss, write_step
from .transfer import g2p, p2g


def tape_gradient(cfg, init, loss, controls, validation=False, state=None):
    """(loss, dL/dF_pc, grad state) through ti.ad.Tape over the forward kernels p2g, grid_op, g2p.

    init: the step-0 particle state {x, v, C, F}; state: a grad-enabled State to reuse, else one is made.
    The production path never calls this: it is the oracle of the tests, `mls-mpm check` and the benchmark.
    """
    runtime.ensure(cfg)
    np_dtype = np.float64 if cfg.dtype == "f64" else np.float32
    t = state
    if t is None:
        t = State(cfg, len(init["x"]), loss_grids=loss.grids, position_loss=isinstance(loss, PositionLoss),
                  colors=isinstance(loss, ColorLoss), needs_grad=True)
        upload_loss(t, loss)
    write_step(t, 0, *(np.asarray(init[k]).astype(np_dtype) for k in ("x", "v", "C", "F")))
    t.F_pc.from_numpy(np.asarray(controls).astype(np_dtype))
    for field in (t.grid_m, t.grid_p, t.grid_v, t.loss, *(g.m for g in t.loss_grids)):
        field.fill(0.0)
    T = cfg.steps
    ot_grids = [g for g in t.loss_grids if g.kind in OT_KINDS]
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
        for field in (t.grid_m, t.grid_p, t.grid_v, t.loss, *(g.m for g in t.loss_grids)):
            field.fill(0.0)
    with ti.ad.Tape(loss=t.loss, validation=validation):
        for f in range(T):
            p2g(t, f)
            grid_op(t, f)
            g2p(t, f)
        for g in t.loss_grids:
            losses.splat(t, g, T)
            if g.kind in OT_KINDS:
                losses.seed_loss(t, g)
            else:
                losses.grid_loss(t, g)
        if t.has_position_loss:
            losses.position_loss(t, T)
    surrogate = sum(float(np.sum(g.seed.to_numpy() * g.m.to_numpy())) for g in ot_grids)
    return t.loss[None] - surrogate + ot_value, t.F_pc.grad.to_numpy().astype(np.float64), t
