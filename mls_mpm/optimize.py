"""Control optimization: Algorithm 1 (gd with line search), adam, lbfgs (thesis 9.1), positions (thesis 8.1).

Every optimizer takes a Simulator whose initial state is set, starting controls and a settings object, and
returns an OptimizeResult. It calls `on_checkpoint(state)` with a dict from which `resume=` continues bit for bit
like an uninterrupted run (on one machine, with a deterministic schedule), and stops early, right after such a
checkpoint, when `should_stop()` turns true (an interrupt). The checkpoints, which are also the points a resume
restarts from:
  gd         after every control step (control k of a temporal iteration done: the state says k + 1), and after
             each temporal iteration's bookkeeping (k = 0 of the next, and whether it converged)
  adam       after every step (controls, both moments)
  lbfgs      after every iteration (iterate, loss, gradient, the curvature pairs in order)
  positions  after every step (the particle positions)
A state records why its optimizer stopped (`stop_reason`, where that is decided after the checkpoint's data), so
a run resumed from its last checkpoint stops where it stopped. `iterations = 0` returns the starting controls and
their loss.
"""
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import SimulationError
from .lbfgs import MEMORY, iterate

ARMIJO = 1e-4  # sufficient decrease: L_new <= L - ARMIJO * step * |g| (normalised) or step * |g|^2 (raw)


# What each optimizer's checkpoint state holds besides "controls" (K, N, 2, 2) and "loss" (a number), by kind:
# int, float, bool, str, floats (a list of numbers), per_control (a list of K numbers), like_controls (an array
# shaped like the controls), particles (an (N, 2) array), pairs (an (h, K N 4) array with h <= lbfgs.MEMORY).
# run.py checks a checkpoint against it before resuming.
_COMMON = {"iteration": "int", "losses": "floats", "grad_norms": "floats"}
STATE = {
    "gd": {**_COMMON, "k": "int", "g_first": "float", "improved": "bool", "small": "bool", "steps": "per_control",
           "stop_reason": "str", "converged": "bool"},
    "adam": {**_COMMON, "m": "like_controls", "v": "like_controls", "g_first": "float"},
    "lbfgs": {**_COMMON, "g": "like_controls", "S": "pairs", "Y": "pairs", "stop_reason": "str", "converged": "bool"},
    "positions": {**_COMMON, "x": "particles"},
}
PAIRS_MAX = MEMORY


@dataclass
class OptimizeResult:
    controls: np.ndarray
    losses: list  # loss after every unit of work, losses[0] the initial loss
    iterations: int  # temporal iterations (gd) or optimizer steps done
    converged: bool
    reason: str
    grad_norms: list = field(default_factory=list)
    positions: np.ndarray = None  # final particle positions of the `positions` optimizer
    loss_start: float = None  # the loss of the starting controls that the run is measured by (schedule.staged)
    restarted: list = field(default_factory=list)  # stages (from 1) whose controls schedule.staged set aside


class Progress:
    """One line per iteration: loss, relative decrease, gradient norm, elapsed time and time left."""

    def __init__(self, total, emit=print, label="iter"):
        self.total, self.emit, self.label = total, emit, label
        self.t0 = time.perf_counter()
        self.first = None

    def update(self, i, loss, grad_norm, initial, extra=""):
        self.first = initial
        elapsed = time.perf_counter() - self.t0
        left = elapsed / max(i, 1) * (self.total - i)
        rel = loss / self.first if self.first else 0.0
        self.emit(f"{self.label} {i}/{self.total}  loss {loss:.6e}  ({rel:.3%} of initial)  |g| {grad_norm:.3e}  "
                  f"elapsed {elapsed:.1f}s  left ~{left:.0f}s{extra}")


def _clip(g, clip):
    """Scale g to norm `clip` when larger (clip = 0: off)."""
    n = float(np.linalg.norm(g))
    return g * (clip / n) if clip and n > clip else g


def gd(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
    """Algorithm 1: temporal iterations over the control timesteps, a line-searched step on control k only.

    The line search starts from lr, halves up to line_search times and accepts only a sufficient decrease
    (ARMIJO); a step accepted at once is doubled for that control's next iteration (kept per control).

    Controls before k are unchanged, so each forward restarts from the stored step k * stride and each
    reverse pass stops there. settings: iterations, step ("normalized" | "raw"), lr, line_search, tol, clip.
    Converged: |g_k| < tol * (first |g|) for every k (normalised; raw: < tol), or no sufficient decrease
    in a whole temporal iteration (thesis 7.3).
    """
    cfg = sim.cfg
    K, s = cfg.n_controls, cfg.stride
    c, st = _start(controls, resume, {"iteration": 0, "k": 0, "losses": [], "grad_norms": [], "g_first": 0.0,
                                      "improved": False, "small": True, "steps": [settings.lr] * K,
                                      "stop_reason": "", "converged": False})
    L = sim.forward(c)  # resumed: also the stored steps that the restarts from step k * s reuse
    if not st["losses"]:
        st["losses"].append(L)
    progress = Progress(settings.iterations, emit, "temporal iteration")
    while st["iteration"] < settings.iterations and not st["stop_reason"]:
        while st["k"] < K:
            k = st["k"]
            start = k * s
            g = _clip(sim.backward(stop=start)[k], settings.clip)
            gn = float(np.linalg.norm(g))
            st["g_first"] = st["g_first"] or gn
            tol = settings.tol * st["g_first"] if settings.step == "normalized" else settings.tol
            if gn > tol:
                st["small"] = False
                direction = g / gn if settings.step == "normalized" else g
                need = gn if settings.step == "normalized" else gn * gn
                step = st["steps"][k]
                accepted = False
                for tries in range(settings.line_search + 1):
                    trial = c.copy()
                    trial[k] -= step * direction
                    try:
                        L_trial = sim.forward(trial, start=start)
                    except SimulationError:  # the trial threw particles off the grid: too long a step
                        L_trial = math.inf
                    if L_trial <= L - ARMIJO * step * need:
                        c, L, accepted = trial, L_trial, True
                        # the next iteration tries twice a step taken at once, else the step that worked
                        st["steps"][k] = 2.0 * step if tries == 0 else step
                        break
                    step *= 0.5
                if accepted:
                    st["improved"] = True
                else:
                    L = sim.forward(c, start=start)  # restore the stored states of the current controls
            st["grad_norms"].append(gn)
            st["k"] = k + 1
            _checkpoint(on_checkpoint, st, c, L)
            if should_stop and should_stop():
                return OptimizeResult(c, st["losses"] + [L], st["iteration"], False, "interrupted",
                                      st["grad_norms"])
        st["losses"].append(L)
        st["iteration"] += 1
        progress.update(st["iteration"], L, max(st["grad_norms"][-K:]), st["losses"][0])
        if st["small"]:
            st["stop_reason"] = "gradient norm below tolerance"
        elif not st["improved"]:
            st["stop_reason"] = "no sufficient decrease in a whole temporal iteration"
        st["converged"] = bool(st["stop_reason"])
        st["k"], st["improved"], st["small"] = 0, False, True
        _checkpoint(on_checkpoint, st, c, L)
        if not st["stop_reason"] and should_stop and should_stop():
            return OptimizeResult(c, st["losses"], st["iteration"], False, "interrupted", st["grad_norms"])
    return OptimizeResult(c, st["losses"], st["iteration"], st["converged"], st["stop_reason"] or "iteration budget",
                          st["grad_norms"])


def adam(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
    """Adam on all control timesteps at once from one backward pass (thesis 9.1). settings: iterations, lr,
    adam_beta1, adam_beta2, tol (relative to the first gradient norm), clip."""
    c, st = _start(controls, resume, {"iteration": 0, "m": np.zeros(np.shape(controls)),
                                      "v": np.zeros(np.shape(controls)), "losses": [], "grad_norms": [],
                                      "g_first": 0.0})
    b1, b2, eps = settings.adam_beta1, settings.adam_beta2, 1e-12
    progress = Progress(settings.iterations, emit, "adam step")
    L = sim.forward(c)
    if not st["losses"]:
        st["losses"].append(L)
    while st["iteration"] < settings.iterations:
        g = _clip(sim.backward(), settings.clip)  # of the forward pass just run on c
        gn = float(np.linalg.norm(g))
        st["g_first"] = st["g_first"] or gn
        if gn <= settings.tol * st["g_first"]:
            return OptimizeResult(c, st["losses"], st["iteration"], True, "gradient norm below tolerance",
                                  st["grad_norms"])
        t = st["iteration"] + 1
        st["m"] = b1 * st["m"] + (1 - b1) * g
        st["v"] = b2 * st["v"] + (1 - b2) * g * g
        m_hat = st["m"] / (1 - b1 ** t)
        v_hat = st["v"] / (1 - b2 ** t)
        c = c - settings.lr * m_hat / (np.sqrt(v_hat) + eps * st["g_first"])
        st["iteration"] = t
        st["grad_norms"].append(gn)
        L = sim.forward(c)  # also the forward pass of the next step's gradient
        st["losses"].append(L)
        progress.update(t, st["losses"][-1], gn, st["losses"][0])
        _checkpoint(on_checkpoint, st, c, st["losses"][-1])
        if should_stop and should_stop():
            return OptimizeResult(c, st["losses"], t, False, "interrupted", st["grad_norms"])
    return OptimizeResult(c, st["losses"], st["iteration"], False, "iteration budget", st["grad_norms"])


def lbfgs(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
    """L-BFGS on all controls at once (thesis 9.1; mls_mpm/lbfgs.py: memory lbfgs.MEMORY = 10 pairs, initial
    Hessian (s.y / y.y) I, strong Wolfe line search with c1 = 1e-4, c2 = 0.9). settings: iterations (L-BFGS
    iterations), tol: stop when an iteration lowers the loss by less than tol * 1e-3 times the loss before it;
    also stops at a zero gradient or when the line search finds no decrease. A trial that leaves the grid
    counts as an infinite loss (the line search shortens the step).

    The checkpoint after every iteration holds the iterate, its loss and gradient and the curvature pairs in
    order, so a resumed run continues bit for bit like an uninterrupted one.
    """
    c, st = _start(controls, resume, {"iteration": 0, "losses": [], "grad_norms": [], "stop_reason": "",
                                      "converged": False})
    shape = c.shape

    def loss(flat):
        try:
            return sim.forward(flat.reshape(shape))
        except SimulationError:  # the trial threw particles off the grid: too long a step
            return math.inf

    def grad():
        return _clip(sim.backward(), settings.clip).ravel()

    if resume is None:
        L = sim.forward(c)
        g, S, Y = grad(), [], []
        st["losses"].append(L)
    else:
        L = float(resume["loss"])
        g = np.array(st.pop("g"), dtype=np.float64).ravel()
        S, Y = (list(np.array(st.pop(k), dtype=np.float64)) for k in ("S", "Y"))
    x = c.ravel()
    progress = Progress(settings.iterations, emit, "lbfgs step")
    while st["iteration"] < settings.iterations and not st["stop_reason"]:
        if not np.any(g):
            st["stop_reason"], st["converged"] = "zero gradient", True
            break
        step = iterate(loss, grad, x, L, g, S, Y)
        if step is None:
            st["stop_reason"] = "the line search found no decrease, not even along -g"
            break
        x, L_new, g, S, Y = step
        decrease, L = L - L_new, L_new
        st["iteration"] += 1
        st["losses"].append(L)
        st["grad_norms"].append(float(np.linalg.norm(g)))
        progress.update(st["iteration"], L, st["grad_norms"][-1], st["losses"][0])
        if decrease < settings.tol * 1e-3 * abs(st["losses"][-2]):
            st["stop_reason"], st["converged"] = "relative loss decrease below tol * 1e-3", True
        n = len(x)
        _checkpoint(on_checkpoint, {**st, "g": g.reshape(shape), "S": np.reshape(S, (len(S), n)),
                                    "Y": np.reshape(Y, (len(Y), n))}, x.reshape(shape), L)
        if not st["stop_reason"] and should_stop and should_stop():
            return OptimizeResult(x.reshape(shape), st["losses"], st["iteration"], False, "interrupted",
                                  st["grad_norms"])
    return OptimizeResult(x.reshape(shape), st["losses"], st["iteration"], st["converged"],
                          st["stop_reason"] or "iteration budget", st["grad_norms"])


def positions(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
    """Thesis 8.1: move the final particle positions directly along -dL/dx (no physics), to study how the
    loss-grid resolution shapes the gradient. Steps of size lr * dx along the normalised gradient, with the
    same sufficient-decrease line search as gd."""
    _, st = _start(controls, resume, {"iteration": 0, "losses": [], "grad_norms": [], "x": sim.state(0)["x"]})
    x = np.array(st["x"], dtype=np.float64)
    L, g = sim.evaluate_positions(x)
    if not st["losses"]:
        st["losses"].append(L)
    progress = Progress(settings.iterations, emit, "positions step")
    while st["iteration"] < settings.iterations:
        gn = float(np.linalg.norm(g))
        if gn == 0.0:
            return OptimizeResult(np.array(controls), st["losses"], st["iteration"], True, "zero gradient",
                                  st["grad_norms"], x)
        step = settings.lr * sim.cfg.dx * math.sqrt(len(x))
        for _ in range(settings.line_search + 1):
            trial = x - step * g / gn
            L_trial, g_trial = sim.evaluate_positions(trial)
            if L_trial <= L - ARMIJO * step * gn:
                x, L, g = trial, L_trial, g_trial
                break
            step *= 0.5
        else:
            return OptimizeResult(np.array(controls), st["losses"], st["iteration"], True,
                                  "no sufficient decrease", st["grad_norms"], x)
        st["iteration"] += 1
        st["losses"].append(L)
        st["grad_norms"].append(gn)
        st["x"] = x
        progress.update(st["iteration"], L, gn, st["losses"][0])
        _checkpoint(on_checkpoint, st, np.array(controls), L)
        if should_stop and should_stop():
            return OptimizeResult(np.array(controls), st["losses"], st["iteration"], False, "interrupted",
                                  st["grad_norms"], x)
    return OptimizeResult(np.array(controls), st["losses"], st["iteration"], False, "iteration budget",
                          st["grad_norms"], x)


def _start(controls, resume, fresh):
    """(controls, state) to start from: a fresh state, or a checkpointed one with its controls."""
    if resume is None:
        return np.array(controls, dtype=np.float64), fresh
    st = {k: v for k, v in resume.items() if k not in ("controls", "loss")}
    st["losses"], st["grad_norms"] = list(st["losses"]), list(st["grad_norms"])
    return np.array(resume["controls"], dtype=np.float64), st


def _checkpoint(on_checkpoint, st, controls, loss):
    if on_checkpoint is not None:
        on_checkpoint({**st, "controls": np.array(controls), "loss": loss})


METHODS = {"gd": gd, "adam": adam, "lbfgs": lbfgs, "positions": positions}
