"""`mls-mpm run`: a scene in, an optimized animation out (thesis Algorithm 1, 7.4), resumable at any point.

Files in the output folder, all written atomically (mode 0666 minus the umask):
  checkpoint.npz  optimizer progress (deleted when the run completes)
  result.npz      controls of every round, initial states, final state, losses (what `render` needs)
  summary.json    scene, loss_initial, loss_final, iou, mass_outside_target, iterations, converged, ...
  frames/, animation.gif, sheet.png, loss.png   (see render_run; a 3D run also particles/ and meshes/)
  .lock           held by the running job (mls_mpm/lock.py), removed when it ends

checkpoint.npz is rewritten at the checkpoints of the optimizer (see mls_mpm/optimize.py: after every control
step of gd, every step of adam and positions, every iteration of lbfgs; at most one every CHECKPOINT_SECONDS,
or less often where writing one takes more than CHECKPOINT_SHARE of that, and always the last one before an
interrupt) and after every finished round; it holds
the finished rounds, the initial state of the next one and the optimizer state of the current one. `--resume`
restarts from the last one written, and ends bit for bit where an uninterrupted run ends. When it records every
round as done (the run was killed while writing its result), the resume only re-simulates the last round and
writes the result. A run never overwrites a folder another job holds, and a finished run removes the renders an
earlier run left there, so a folder never mixes two runs. A 3D scene (sim.dim = 3) writes the same files, its
arrays with dim entries per vector (x (N, 3), controls (K, N, 3, 3), target grids (res, res, res)).
"""
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from . import problem as problems, runtime
from .checkpoint import (TEMP_GLOB, CheckpointError, OutputError, atomic_write, check_array, check_value, load_npz,
                         save_json, save_npz, split_state)
from .errors import Interrupted
from .images import splat_grid
from .lock import folder_lock
from .optimize import METHODS, PAIRS_MAX, STATE, OptimizeResult
from .schedule import BUDGET_REASON, STAGE_STATE, Stage, staged
from .result import STATE_KEYS, state_shapes
from .simulator import Simulator

__all__ = ["OutputError", "prepare_out", "fingerprint", "run_scene"]

RENDER_OUTPUTS = ("frames", "animation.gif", "sheet.png", "loss.png", "animation.mp4",  # what render_run makes
                  "particles", "meshes")  # and, for a 3D run, its PLY sequences (export3d.PARTICLES_DIR, MESHES_DIR)
SEQUENCE_DIRS = ("frames", "particles", "meshes")  # folders of render_run's numbered files
MISMATCHES_SHOWN = 3  # settings named in a resume refusal before "and N more"


def prepare_out(out_dir):
    """Create the output folder and prove it writable, with a one-line error otherwise."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise OutputError(f"{out}: output folder is not writable ({e.strerror or e}); pick another with --out") from None
    return out


def fingerprint(scene):
    """What a checkpoint must share with the scene to be resumed: all but render and the iteration and time
    budgets."""
    d = scene.to_dict()
    d.pop("render")
    d["optimize"] = {k: v for k, v in d["optimize"].items() if k not in ("iterations", "max_seconds")}
    d["scene"] = {k: v for k, v in d["scene"].items() if k != "name"}
    return json.dumps(d, sort_keys=True)


def _initial_state(prob):
    N, d = prob.x0.shape
    return {"x": prob.x0, "v": np.zeros((N, d)), "C": np.zeros((N, d, d)), "F": np.tile(np.eye(d), (N, 1, 1))}


def run_scene(scene, out_dir, resume=False, emit=print, should_stop=None, render=True, files=None):
    """Optimize a scene's controls (all rounds), write result.npz, summary.json and the renders.

    Returns the summary dict; summary["interrupted"] is true when should_stop() ended the run early, in
    which case checkpoint.npz holds everything needed to continue with resume=True (or, with
    summary["render_interrupted"], the result is complete and only its rendering was stopped). files: {name:
    text} written atomically into the output folder once it is created and locked (morph's scene.toml).
    """
    t0 = time.perf_counter()
    prob = problems.build(scene)
    ckpt = Path(out_dir) / "checkpoint.npz"
    if resume and not ckpt.is_file():  # before anything is created
        raise CheckpointError(f"{ckpt}: no such file; expected the checkpoint of an interrupted run (drop --resume "
                              "to start over)")
    cfg = _resumed_config(ckpt, scene.sim) if resume else scene.sim
    sim = Simulator(cfg, prob.x0, loss=prob.loss)  # refuses a missing backend or too little memory: nothing written
    out = prepare_out(out_dir)
    with folder_lock(out, "run"):
        for name, text in (files or {}).items():
            atomic_write(out / name, lambda fh, text=text: fh.write(text.encode()))
        return _run(scene, prob, sim, out, resume, emit, should_stop, render, t0)


def _resumed_config(path, cfg):
    """The simulation settings to resume the checkpoint at path with: under `sim.schedule = "auto"`, the schedule
    the checkpoint was made in. `auto` can resolve otherwise in the resumed process (it follows the CPUs this
    process may run on and whether it may pin threads to them, config.pins_workers, which a resume elsewhere or
    under another CPU mask can change), and the two schedules differ in round-off, which a bit-for-bit resume must
    repeat. A checkpoint that names none (written before checkpoints did) resumes under `auto`."""
    if cfg.schedule != "auto":
        return cfg  # the scene's own schedule, which the checkpoint's fingerprint holds
    meta, _ = load_npz(path, "checkpoint", meta_only=True)  # _load_checkpoint reads the arrays
    schedule = meta.get("schedule")
    if schedule is None:
        return cfg
    if schedule not in ("serial", "parallel"):
        raise CheckpointError(f"{path}: schedule is {json.dumps(schedule)[:40]}: expected \"serial\" or \"parallel\"; "
                              "not a checkpoint of this program; delete it or re-run")
    return cfg.replace(schedule=schedule)


def stages(scene, round_index=0):
    """The stages of optimize.schedule, or one stage of every loss grid; rounds after the first run the last
    stage alone (they start where the round before ended, near the target: the coarse stages, which pull far
    material, would only spend their share of the time)."""
    plan = scene.optimize.schedule or ({"grids": scene.loss.grids, "share": 1.0},)
    plan = plan if round_index == 0 else plan[-1:]
    return [Stage(tuple(s["grids"]), s["share"]) for s in plan]


def _state_kinds(scene, round_index):
    """What the checkpoint of this scene's optimizer in round round_index holds (mls_mpm.optimize.STATE), with
    the stage's part."""
    kinds = dict(STATE[scene.optimize.method])
    return {**kinds, **STAGE_STATE} if len(stages(scene, round_index)) > 1 else kinds


def _run(scene, prob, sim, out, resume, emit, should_stop, render, t0):
    cfg, opt = scene.sim, scene.optimize
    for note in prob.notes:
        emit(note)
    emit(f"{scene.name}: {len(prob.x0)} particles, {cfg.n_grid}^{cfg.dim} grid, {cfg.steps} steps, "
         f"{cfg.n_controls} control steps, loss {scene.loss.kind} on grids {list(scene.loss.grids)}, "
         f"optimizer {opt.method}, {opt.rounds} round(s), on {runtime.running_arch()} ({sim.schedule} schedule)")
    _remove_temp_files(out, emit)
    ckpt = out / "checkpoint.npz"
    done, starts, opt_state, elapsed = [], [_initial_state(prob)], None, 0.0
    if resume:
        done, starts, opt_state, elapsed = _load_checkpoint(ckpt, scene, prob)
        emit(f"resuming from {ckpt}: " + (f"round {len(done) + 1} of {opt.rounds}" if len(done) < opt.rounds
                                          else "every round is done; writing the result"))
    deadline = t0 - elapsed + opt.max_seconds if opt.max_seconds > 0 else math.inf
    while len(done) < opt.rounds:
        r = len(done)
        now = time.perf_counter()
        # the budget left is split over the rounds left in the proportions R - r : ... : 2 : 1 (round r of R, from
        # 0), this one taking 2 / (R - r + 1) of it: the first round, which has the farthest to go, gets the most,
        # and what a round leaves unused goes to the later ones
        seconds = max((deadline - now) * 2 / (opt.rounds - r + 1), 1e-9) if math.isfinite(deadline) else 0.0
        method = staged(METHODS[opt.method], stages(scene, r), seconds, now)
        sim.set_initial(**starts[r])

        saver = _Throttled(lambda state, at: _save_checkpoint(ckpt, scene, sim.schedule, done, starts, state,
                                                                elapsed + at - t0))
        if opt.rounds > 1:
            emit(f"round {r + 1}/{opt.rounds}")
        res = method(sim, sim.zero_controls(), opt, on_checkpoint=saver, should_stop=should_stop,
                     emit=emit, resume=opt_state)
        opt_state = None
        if res.reason == "interrupted":
            saver.flush()  # the state the optimizer checkpointed just before it returned
            emit(f"interrupted: progress saved to {ckpt}; continue with --resume")
            return {"scene": scene.name, "interrupted": True, "wall_seconds": elapsed + time.perf_counter() - t0}
        done.append(res)
        if res.reason == BUDGET_REASON and time.perf_counter() >= deadline:
            emit(f"stopped at the time budget of {opt.max_seconds:g} s after {len(done)} of {opt.rounds} round(s)")
            break
        if len(done) < opt.rounds:
            starts.append(_next_start(scene, prob, sim, starts[r], res))
        _save_checkpoint(ckpt, scene, sim.schedule, done, starts, None, elapsed + time.perf_counter() - t0)
    wall = elapsed + time.perf_counter() - t0
    summary = _finish(scene, prob, sim, done, starts, out, wall, emit)
    ckpt.unlink(missing_ok=True)
    if render:
        from .render_run import render_run

        try:
            render_run(out, emit=emit, should_stop=should_stop, sim=sim)  # sim: its kernels are built already
        except Interrupted:
            emit(f"rendering interrupted: the result is saved in {out}; `mls-mpm render {out}` renders it")
            return {**summary, "interrupted": True, "render_interrupted": True}
    emit(f"loss {summary['loss_initial']:.6e} -> {summary['loss_final']:.6e}, iou {problems.iou_text(summary['iou'])}, "
         f"mass outside target {summary['mass_outside_target']:.3f}, {wall:.1f} s; results in {out}")
    return summary


def _final_state(scene, sim, start, res):
    """The state of the last step of a finished round, re-simulated from its initial state and controls."""
    sim.set_initial(**start)
    sim.forward(res.controls)
    final = sim.state(scene.sim.steps)
    if res.positions is not None:  # the `positions` study moves the final particles directly
        final["x"] = res.positions
    return final


def _next_start(scene, prob, sim, start, res):
    """Initial state of the round after `res`: its final positions (and v, C, F with carry_state)."""
    final = _final_state(scene, sim, start, res)
    keep = STATE_KEYS if scene.optimize.carry_state else ("x",)
    return {**_initial_state(prob), **{k: final[k] for k in keep}}


def _finish(scene, prob, sim, done, starts, out, wall, emit):
    cfg = scene.sim
    final_x = _final_state(scene, sim, starts[len(done) - 1], done[-1])["x"]
    finest = int(np.argmax(scene.loss.grids))
    res = scene.loss.grids[finest]
    target = prob.target_mass_grids[finest]
    mass = splat_grid(final_x, cfg.m_p, res)
    rest = problems.rest_node_mass(cfg, res)
    losses = [L for r in done for L in r.losses]
    summary = {
        "scene": scene.name,
        "loss_initial": done[0].loss_start if done[0].loss_start is not None else done[0].losses[0],
        "loss_final": done[-1].losses[-1],
        "iou": problems.target_iou(mass, target, rest),
        "mass_outside_target": problems.mass_outside(mass, target),
        "mass_error": problems.mass_error(mass, target),
        "iterations": sum(r.iterations for r in done),
        "converged": all(r.converged for r in done),
        "stop_reason": [r.reason for r in done],
        # per round, the stages (from 1) whose controls raised the measured loss and were set aside (schedule._kept)
        "stages_restarted": [r.restarted for r in done],
        "wall_seconds": wall,
        "particles": len(prob.x0),
        "dim": cfg.dim,
        "backend": runtime.running_arch(),  # what Taichi ran on: "cpu", "cuda" or "vulkan"
        "schedule": sim.schedule,  # what sim.schedule ran as: "serial" or "parallel" (`auto` resolved)
        "settings": scene.to_dict(),
    }
    arrays = {
        "controls": np.stack([r.controls for r in done]),
        "losses": np.array(losses),
        "round_lengths": np.array([len(r.losses) for r in done]),
        "colors": prob.colors,
        "target_grid": target,
        "final_x": final_x,
        **{f"init_{k}": np.stack([s[k] for s in starts[:len(done)]]) for k in STATE_KEYS},
    }
    if scene.loss.kind == "color":
        m_t = problems.target_particle_mass(scene, len(prob.x0), len(prob.target_points))
        target_color = splat_grid(prob.target_points, m_t, res, prob.target_colors)
        summary["color_error"] = problems.color_error(splat_grid(final_x, cfg.m_p, res, prob.colors), target_color)
    if prob.target_x is not None:
        arrays["target_x"] = prob.target_x
    if prob.target_points is not None:
        arrays["target_points"] = prob.target_points
        arrays["target_colors"] = prob.target_colors
    _remove_stale_renders(out, emit)
    save_npz(out / "result.npz", {"summary": {k: v for k, v in summary.items() if k != "settings"},
                                  "settings": summary["settings"], "method": scene.optimize.method}, arrays)
    save_json(out / "summary.json", summary)
    return summary


def _remove_temp_files(out, emit):
    """Temp files of atomic writes that a killed process left in the folder or its frames/."""
    stale = [p for d in (out, *(out / n for n in SEQUENCE_DIRS)) if d.is_dir() for p in d.glob(TEMP_GLOB)
             if p.is_file()]
    for p in stale:
        p.unlink(missing_ok=True)
    if stale:
        emit(f"removed {len(stale)} temp file(s) left in {out} by a killed run")


def _remove_stale_renders(out, emit):
    """The renders of an earlier run in the folder, which would otherwise sit beside this run's result."""
    found = [name for name in RENDER_OUTPUTS if (out / name).exists() or (out / name).is_symlink()]
    for name in found:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    if found:
        emit(f"removed the renders of an earlier run from {out}: "
             + ", ".join(n + ("/" if n in SEQUENCE_DIRS else "") for n in found))


# The optimizers checkpoint after every iteration (an L-BFGS state at 64^2 is ~12 MB: 9% of a morph's time when
# every one was written); a checkpoint less than CHECKPOINT_SECONDS after the last one written is held back, and
# written if the optimizer then returns interrupted (its last act before returning). So an interrupt (Ctrl-C,
# SIGTERM) loses nothing; a kill that gives no chance to save (SIGKILL, power loss) loses at most this much work.
# A large state waits longer, so that writing takes at most CHECKPOINT_SHARE of the run: the next write waits the
# last write's time / CHECKPOINT_SHARE if that is more. A 3D L-BFGS state of 5,544 particles (10 controls) is 84 MiB,
# written in 0.10-0.19 s on the AMD EPYC of BENCHMARKS.md, where the wait changes nothing measurable (a 40-iteration
# run: 28.9 s before, 29.6 s after); one of 20,000 particles is 302 MiB, 0.38-1.2 s a write, up to a third of a run that
# wrote one every 2 s.
CHECKPOINT_SECONDS = 2.0
CHECKPOINT_SHARE = 0.05


class _Throttled:
    """on_checkpoint for an optimizer: write(state, clock reading) at most every CHECKPOINT_SECONDS, or every
    (the last write's time / CHECKPOINT_SHARE) if that is longer; flush() writes the state held back, if any (only
    right after the optimizer returned: its arrays are unchanged)."""

    def __init__(self, write, clock=time.perf_counter):
        self.write, self.clock, self.last, self.held = write, clock, -math.inf, None
        self.wait = CHECKPOINT_SECONDS

    def __call__(self, state):
        now = self.clock()
        if now - self.last >= self.wait:
            self.write(state, now)
            self.wait = max(CHECKPOINT_SECONDS, (self.clock() - now) / CHECKPOINT_SHARE)
            self.last, self.held = now, None
        else:
            self.held = (state, now)

    def flush(self):
        if self.held is not None:
            self.write(*self.held)
            self.held = None


# checkpoint entries added after checkpoints were first written, and their value in a checkpoint without them (an
# older version's run resumed by this one): no stage set aside
LATER_KEYS = {"restarted": [], "stage_restarts": []}


def _save_checkpoint(path, scene, schedule, done, starts, opt_state, elapsed):
    """schedule: the one the run steps in (Simulator.schedule), which a resume under `auto` keeps (_resumed_config)."""
    meta = {"fingerprint": fingerprint(scene), "elapsed": elapsed, "schedule": schedule,
            "rounds": [{"losses": r.losses, "iterations": r.iterations, "converged": r.converged,
                        "reason": r.reason, "grad_norms": r.grad_norms, "restarted": r.restarted} for r in done]}
    arrays = {f"start_{k}": np.stack([s[k] for s in starts]) for k in STATE_KEYS}
    for i, r in enumerate(done):
        arrays[f"round_controls_{i}"] = r.controls
        if r.positions is not None:
            arrays[f"round_positions_{i}"] = r.positions
    if opt_state is not None:
        opt_meta, opt_arrays = split_state(opt_state)
        meta["opt"] = opt_meta
        arrays.update({f"opt_{k}": v for k, v in opt_arrays.items()})
    save_npz(path, meta, arrays)


def _load_checkpoint(path, scene, prob):
    """(done rounds, initial states, optimizer state or None, elapsed seconds) of a checkpoint, each part
    checked against the scene: CheckpointError names the file, the entry and what was expected."""
    meta, arrays = load_npz(path, "checkpoint")
    what = "checkpoint"
    theirs = meta.get("fingerprint")
    if theirs != fingerprint(scene):
        raise CheckpointError(f"{path}: made with other scene settings ({_differences(theirs, fingerprint(scene))}); "
                              "drop --resume to start over, or use the settings it was made with")
    opt = scene.optimize
    K, N, d = scene.sim.n_controls, len(prob.x0), scene.sim.dim
    controls = (K, N, d, d)
    rounds = meta.get("rounds")
    if not isinstance(rounds, list) or len(rounds) > opt.rounds:
        raise CheckpointError(f"{path}: rounds is {json.dumps(rounds)[:40]}: expected a list of at most {opt.rounds} "
                              f"finished round(s); not a {what} of this scene; delete it or re-run")
    done = []
    for i, r in enumerate(rounds):
        check_value(path, f"rounds[{i}]", r, "table", what)
        v = {key: check_value(path, f"rounds[{i}].{key}", r.get(key, LATER_KEYS.get(key)), kind, what)
             for key, kind in (("losses", "floats"), ("iterations", "int"), ("converged", "bool"), ("reason", "str"),
                               ("grad_norms", "floats"), ("restarted", "ints"))}
        _require_losses(path, f"rounds[{i}].losses", v["losses"])
        positions = None
        if opt.method == "positions":
            positions = check_array(path, arrays, f"round_positions_{i}", "f", (N, d), what)
        done.append(OptimizeResult(check_array(path, arrays, f"round_controls_{i}", "f", controls, what),
                                   v["losses"], v["iterations"], v["converged"], v["reason"], v["grad_norms"],
                                   positions, restarted=v["restarted"]))
    n_starts = min(len(done) + 1, opt.rounds)
    for k in STATE_KEYS:
        check_array(path, arrays, f"start_{k}", "f", (n_starts, N, *state_shapes(d)[k]), what)
    starts = [{k: arrays[f"start_{k}"][i] for k in STATE_KEYS} for i in range(n_starts)]
    opt_state = None
    if "opt" in meta and len(done) < opt.rounds:
        st = check_value(path, "opt", meta["opt"], "table", what)
        opt_state = {"loss": check_value(path, "opt.loss", st.get("loss"), "float", what),
                     "controls": check_array(path, arrays, "opt_controls", "f", controls, what)}
        shapes = {"like_controls": controls, "particles": (N, d), "pairs": (None, K * N * d * d)}
        kinds = _state_kinds(scene, len(done))
        for key, kind in kinds.items():
            if kind in shapes:
                opt_state[key] = check_array(path, arrays, f"opt_{key}", "f", shapes[kind], what)
            elif kind == "per_control":
                opt_state[key] = check_value(path, f"opt.{key}", st.get(key), "floats", what, length=K)
            else:
                opt_state[key] = check_value(path, f"opt.{key}", st.get(key, LATER_KEYS.get(key)), kind, what)
        _require_losses(path, "opt.losses", opt_state["losses"])
        pairs = [opt_state[k] for k, kind in kinds.items() if kind == "pairs"]
        if pairs and (len({len(p) for p in pairs}) != 1 or len(pairs[0]) > PAIRS_MAX):
            raise CheckpointError(f"{path}: opt_S and opt_Y hold {len(pairs[0])} and {len(pairs[-1])} pairs: "
                                  f"expected as many of each, at most {PAIRS_MAX}; delete it or re-run")
    elapsed = check_value(path, "elapsed", meta.get("elapsed", 0.0), "float", what)
    return done, starts, opt_state, float(elapsed)


def _require_losses(path, where, losses):
    if not losses:
        raise CheckpointError(f"{path}: {where} is empty: expected the loss of the starting controls at least; "
                              "delete it or re-run")


def _differences(theirs, ours):
    """'sim.steps: 150 in the checkpoint, 100 now; ...' for the settings two fingerprints disagree on."""
    try:
        old = json.loads(theirs)
    except (TypeError, ValueError):
        return "it records no readable settings"
    if not isinstance(old, dict):
        return "it records no readable settings"
    a, b = dict(_flat(old)), dict(_flat(json.loads(ours)))
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k, _ABSENT) != b.get(k, _ABSENT))
    shown = [f"{k}: {_show(a.get(k, _ABSENT))} in the checkpoint, {_show(b.get(k, _ABSENT))} now"
             for k in keys[:MISMATCHES_SHOWN]]
    more = len(keys) - len(shown)
    return "; ".join(shown) + (f"; and {more} more" if more > 0 else "") if shown else "unknown differences"


_ABSENT = object()


def _flat(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flat(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def _show(v):
    return "absent" if v is _ABSENT else json.dumps(v)
