"""Control optimization: Algorithm 1 (gd with line search), adam, lbfgs (thesis 9.1), positions (thesis 8.1).

Every optimizer takes a Simulator whose initial state is set, starting controls and a settings object, and
returns an OptimizeResult. It calls `on_checkpoint(state)` after each unit of work (a control step of gd, an
adam or lbfgs step) with a dict from which `resume=` continues exactly, and stops early, after such a
checkpoint, when `should_stop()` turns true (an interrupt).
"""
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .errors import SimulationError

ARMIJO = 1e-4  # sufficient decrease: L_new <= L - ARMIJO * step * |g| (normalised) or step * |g|^2 (raw)


@dataclass
class OptimizeResult:
    controls: np.ndarray
    losses: list  # loss after every unit of work, losses[0] the initial loss
    iterations: int  # temporal iterations (gd) or optimizer steps done
    converged: bool
    reason: str
    grad_norms: list = field(default_factory=list)
    positions: np.ndarray = None  # final particle positions of the `positions` optimizer


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
                                      "improved": False, "small": True, "steps": [settings.lr] * K})
    st.setdefault("small", True)
    L = sim.forward(c)
    if not st["losses"]:
        st["losses"].append(L)
    progress = Progress(settings.iterations, emit, "temporal iteration")
    reason = "iteration budget"
    converged = False
    while st["iteration"] < settings.iterations:
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
            if should_stop and should_stop():
                _checkpoint(on_checkpoint, st, c, L)
                return OptimizeResult(c, st["losses"] + [L], st["iteration"], False, "interrupted",
                                      st["grad_norms"])
        st["losses"].append(L)
        st["iteration"] += 1
        progress.update(st["iteration"], L, max(st["grad_norms"][-K:]), st["losses"][0])
        improved, small = st["improved"], st["small"]
        st["k"], st["improved"], st["small"] = 0, False, True
        _checkpoint(on_checkpoint, st, c, L)
        if small:
            converged, reason = True, "gradient norm below tolerance"
            break
        if not improved:
            converged, reason = True, "no sufficient decrease in a whole temporal iteration"
            break
        if should_stop and should_stop():
            return OptimizeResult(c, st["losses"], st["iteration"], False, "interrupted", st["grad_norms"])
    return OptimizeResult(c, st["losses"], st["iteration"], converged, reason, st["grad_norms"])


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


class _Interrupted(Exception):
    pass


def lbfgs(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
    """L-BFGS-B from scipy.optimize on all controls at once (thesis 9.1). settings: iterations, tol.

    A resumed run restarts L-BFGS's curvature memory from the checkpointed controls.
    """
    from scipy.optimize import minimize

    c0, st = _start(controls, resume, {"iteration": 0, "losses": [], "grad_norms": []})
    shape = c0.shape
    progress = Progress(settings.iterations, emit, "lbfgs step")
    last = {}

    def fun(flat):
        L = sim.forward(flat.reshape(shape))
        g = _clip(sim.backward(), settings.clip)
        last.update(L=L, gn=float(np.linalg.norm(g)))
        if not st["losses"]:
            st["losses"].append(L)
        return L, g.ravel()

    def callback(xk):
        st["iteration"] += 1
        st["losses"].append(last["L"])
        st["grad_norms"].append(last["gn"])
        progress.update(st["iteration"], last["L"], last["gn"], st["losses"][0])
        _checkpoint(on_checkpoint, st, xk.reshape(shape), last["L"])
        if should_stop and should_stop():
            raise _Interrupted(xk.copy())

    left = settings.iterations - st["iteration"]
    if left <= 0:
        return OptimizeResult(c0, st["losses"], st["iteration"], False, "iteration budget", st["grad_norms"])
    try:
        res = minimize(fun, c0.ravel(), jac=True, method="L-BFGS-B", callback=callback,
                       options={"maxiter": left, "gtol": 0.0, "ftol": settings.tol * 1e-3})
    except _Interrupted as stop:
        return OptimizeResult(stop.args[0].reshape(shape), st["losses"], st["iteration"], False, "interrupted",
                              st["grad_norms"])
    converged = res.status == 0 and st["iteration"] < settings.iterations
    return OptimizeResult(res.x.reshape(shape), st["losses"], st["iteration"], converged, str(res.message),
                          st["grad_norms"])


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
