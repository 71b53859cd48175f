"""Coarse-to-fine stages and a wall-clock budget around one optimizer (thesis 8.1 by hand, here as a plan).

`optimize.schedule` is a list of stages, each a set of loss-grid resolutions (a subset of loss.grids) and its
share of `optimize.iterations` (and of the time budget). Stage s runs the optimizer on the loss of its grids
alone, starting from the controls stage s - 1 ended with, with a fresh optimizer state (the loss changed, so
L-BFGS's curvature pairs and Adam's moments no longer describe it). Coarse grids first: their wider kernels
(and the optimal-transport cost) pull material that is far from the target; the finer grids added later shape
the detail. Without a schedule there is one stage holding every loss grid.

The budget (`optimize.max_seconds`, 0: none) is a deadline for the whole run, compile time included. The
kernels are compiled first (one forward and backward pass), then a stage that starts with R seconds left gets
R * its share / the shares left; one that finishes early leaves its time to the next. A stage whose controls
leave the measured loss (every grid's, the last stage's) above that of the run's starting controls hands the next
stage those starting controls instead (`_kept`), and the result lists it in `restarted` (summary.json:
`stages_restarted`). An optimizer past its deadline stops after its current unit of work, like an interrupt, and
its controls (the best so far: every optimizer here only accepts decreases, except adam) are the result, with the
stop reason "time budget".

The checkpoint of a staged run is the inner optimizer's state plus STAGE_STATE: which stage it is in, and the
losses, gradient norms and iterations of the stages before, and which of them were set aside. A stage that had
finished when the run was interrupted resumes to its own end at once (its optimizer state says it stopped), so a
resumed run follows the same stages bit for bit.
"""
import math
import time
from dataclasses import dataclass, replace

from .optimize import OptimizeResult

STAGE_STATE = {"stage": "int", "stage_losses": "floats", "stage_grad_norms": "floats", "stage_iterations": "int",
               "loss_start": "float", "stage_restarts": "ints"}
BUDGET_REASON = "time budget"


@dataclass(frozen=True)
class Stage:
    grids: tuple  # loss-grid resolutions whose terms are on in this stage
    share: float  # its part of optimize.iterations and of the time budget


def stage_iterations(total, shares):
    """Iterations of each stage: total split in proportion to shares, rounded so they add up to total."""
    whole = sum(shares)
    edges = [round(total * sum(shares[:k]) / whole) for k in range(len(shares) + 1)]
    return [b - a for a, b in zip(edges, edges[1:])]


def staged(method, stages, max_seconds=0.0, started=None, clock=time.perf_counter):
    """An optimizer with method's signature that runs `stages` one after the other within max_seconds.

    started: the clock reading the budget counts from (default: now); a resumed run passes now minus the time
    it had already spent. The returned OptimizeResult concatenates the stages' losses (each stage's list starts
    with its own loss of the controls it started from) and adds their iterations; its `loss_start` is the last
    stage's loss (every grid's) of the starting controls, the loss the run is measured by; its `restarted` the
    stages (from 1) whose controls were set aside for the starting ones (_kept).
    """
    t0 = clock() if started is None else started
    deadline = t0 + max_seconds if max_seconds > 0 else math.inf

    def run(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
        counts = stage_iterations(settings.iterations, [s.share for s in stages])
        multi = len(stages) > 1
        first, losses, grad_norms, iterations, loss_start, inner = 0, [], [], 0, None, resume
        restarted = []
        if resume is not None and multi:
            inner = {k: v for k, v in resume.items() if k not in STAGE_STATE}
            first, iterations, loss_start = int(resume["stage"]), int(resume["stage_iterations"]), resume["loss_start"]
            losses, grad_norms = list(resume["stage_losses"]), list(resume["stage_grad_norms"])
            restarted = [int(k) for k in resume["stage_restarts"]]
        if multi and loss_start is None:
            sim.set_active_grids(stages[-1].grids)
            loss_start = sim.forward(controls)
        if math.isfinite(deadline):  # compile the forward and reverse kernels before the stages' clocks start
            sim.set_active_grids(stages[-1].grids)
            sim.forward(controls if inner is None else inner["controls"])
            sim.backward()
        c = controls if inner is None else inner["controls"]
        for k in range(first, len(stages)):
            stage = stages[k]
            sim.set_active_grids(stage.grids)
            shares_left = sum(s.share for s in stages[k:])
            now = clock()
            stage_deadline = now + (deadline - now) * stage.share / shares_left if math.isfinite(deadline) else deadline
            if multi:
                emit(f"stage {k + 1}/{len(stages)}: loss grids {list(stage.grids)}, {counts[k]} iterations"
                     + (f", {max(stage_deadline - now, 0.0):.0f} s" if math.isfinite(deadline) else ""))

            def checkpoint(state, k=k):
                if on_checkpoint is None:
                    return
                if multi:
                    state = {**state, "stage": k, "stage_losses": losses, "stage_grad_norms": grad_norms,
                             "stage_iterations": iterations, "loss_start": loss_start, "stage_restarts": restarted}
                on_checkpoint(state)

            def stop(stage_deadline=stage_deadline):
                return bool(should_stop and should_stop()) or clock() >= stage_deadline

            res = method(sim, c, replace(settings, iterations=counts[k]), on_checkpoint=checkpoint, should_stop=stop,
                         emit=emit, resume=inner if k == first else None)
            inner = None
            if res.reason == "interrupted" and should_stop and should_stop():
                return _result(res, losses, grad_norms, iterations, loss_start, restarted)
            if res.reason == "interrupted":  # past the stage's deadline; the next stage gets what is left
                res.reason, res.converged = BUDGET_REASON, False
                out_of_time = clock() >= deadline
                if out_of_time and k < len(stages) - 1 and res.positions is None:
                    # no time for the later stages: the run still ends with the last stage's loss of its controls
                    # (a list of one, as a stage of no iterations), measured like loss_start, not stage k's
                    losses, grad_norms = losses + list(res.losses), grad_norms + list(res.grad_norms)
                    iterations += res.iterations
                    kept, measured, aside = _kept(sim, stages, k, res.controls, controls, loss_start, emit)
                    restarted = restarted + [k + 1] * aside
                    res = OptimizeResult(kept, [measured], 0, False, BUDGET_REASON)
                if k == len(stages) - 1 or out_of_time:
                    sim.set_active_grids(None)
                    return _result(res, losses, grad_norms, iterations, loss_start, restarted)
            c = res.controls
            if k < len(stages) - 1:
                losses, grad_norms = losses + list(res.losses), grad_norms + list(res.grad_norms)
                iterations += res.iterations
                c, _, aside = _kept(sim, stages, k, c, controls, loss_start, emit)
                restarted = restarted + [k + 1] * aside
        sim.set_active_grids(None)
        return _result(res, losses, grad_norms, iterations, loss_start, restarted)

    return run


def _kept(sim, stages, k, c, start, loss_start, emit):
    """(controls, their loss the run is measured by: the last stage's, whether c was set aside) that stage k + 1
    starts from, or the run ends with when out of time: stage k's controls c, unless they leave that loss above
    loss_start, that of the run's starting controls: then those and loss_start (a coarse loss can be lowered by
    breaking the body into blobs that the fine loss then cannot undo; the later stages would start worse off than
    from nothing). Deterministic, so a resumed run decides the same."""
    sim.set_active_grids(stages[-1].grids)
    measured = sim.forward(c)
    if measured <= loss_start:
        return c, measured, False
    emit(f"stage {k + 1}/{len(stages)} left the loss of grids {list(stages[-1].grids)} at {measured:.6e}, above "
         f"its {loss_start:.6e} at the start: going on from the starting controls instead")
    return start, loss_start, True


def _result(res, losses, grad_norms, iterations, loss_start, restarted):
    """The last stage's result with the earlier stages' losses, gradient norms, iterations and set-aside stages."""
    return OptimizeResult(res.controls, losses + list(res.losses), iterations + res.iterations, res.converged,
                          res.reason, grad_norms + list(res.grad_norms), res.positions,
                          res.losses[0] if loss_start is None else loss_start, list(restarted))
