"""`mls-mpm run`: a scene in, an optimized animation out (thesis Algorithm 1, 7.4), resumable at any point.

Files in the output folder, all written atomically:
  checkpoint.npz  optimizer progress after every unit of work (deleted when the run completes)
  result.npz      controls of every round, initial states, final state, losses (what `render` needs)
  summary.json    scene, loss_initial, loss_final, iou, mass_outside_target, iterations, converged, ...
  frames/, animation.gif, sheet.png, loss.png   (see render_run)
"""
import json
import time
from pathlib import Path

import numpy as np

from . import problem as problems, runtime
from .checkpoint import CheckpointError, load_npz, save_json, save_npz, split_state
from .images import splat_grid
from .optimize import METHODS
from .result import STATE_KEYS
from .simulator import Simulator
from .errors import UserError

class OutputError(UserError):
    """The output folder cannot be used."""


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
    """What a checkpoint must share with the scene to be resumed: all but render and the iteration budget."""
    d = scene.to_dict()
    d.pop("render")
    d["optimize"] = {k: v for k, v in d["optimize"].items() if k != "iterations"}
    d["scene"] = {k: v for k, v in d["scene"].items() if k != "name"}
    return json.dumps(d, sort_keys=True)


def _initial_state(prob):
    N = len(prob.x0)
    return {"x": prob.x0, "v": np.zeros((N, 2)), "C": np.zeros((N, 2, 2)), "F": np.tile(np.eye(2), (N, 1, 1))}


def run_scene(scene, out_dir, resume=False, emit=print, should_stop=None, render=True):
    """Optimize a scene's controls (all rounds), write result.npz, summary.json and the renders.

    Returns the summary dict; summary["interrupted"] is true when should_stop() ended the run early, in
    which case checkpoint.npz holds everything needed to continue with resume=True.
    """
    t0 = time.perf_counter()
    prob = problems.build(scene)
    cfg, opt = scene.sim, scene.optimize
    sim = Simulator(cfg, prob.x0, loss=prob.loss)  # refuses a missing backend or too little memory: nothing written
    out = prepare_out(out_dir)
    emit(f"{scene.name}: {len(prob.x0)} particles, {cfg.n_grid}^2 grid, {cfg.steps} steps, "
         f"{cfg.n_controls} control steps, loss {scene.loss.kind} on grids {list(scene.loss.grids)}, "
         f"optimizer {opt.method}, {opt.rounds} round(s), on {runtime.running_arch()}")
    ckpt = out / "checkpoint.npz"
    done, starts, opt_state, elapsed = [], [_initial_state(prob)], None, 0.0
    if resume:
        done, starts, opt_state, elapsed = _load_checkpoint(ckpt, scene)
        emit(f"resuming from {ckpt}: round {len(done) + 1} of {opt.rounds}")
    method = METHODS[opt.method]
    interrupted = False
    while len(done) < opt.rounds:
        r = len(done)
        sim.set_initial(**starts[r])

        def on_checkpoint(state):
            _save_checkpoint(ckpt, scene, done, starts, state, elapsed + time.perf_counter() - t0)

        if opt.rounds > 1:
            emit(f"round {r + 1}/{opt.rounds}")
        res = method(sim, sim.zero_controls(), opt, on_checkpoint=on_checkpoint, should_stop=should_stop,
                     emit=emit, resume=opt_state)
        opt_state = None
        if res.reason == "interrupted":
            interrupted = True
            break
        done.append(res)
        sim.forward(res.controls)
        final = sim.state(cfg.steps)
        if res.positions is not None:
            final["x"] = res.positions
        nxt = {"x": final["x"]}
        if opt.carry_state:
            nxt.update(v=final["v"], C=final["C"], F=final["F"])
        starts.append({**_initial_state(prob), **nxt})
        _save_checkpoint(ckpt, scene, done, starts, None, elapsed + time.perf_counter() - t0)
    wall = elapsed + time.perf_counter() - t0
    if interrupted:
        emit(f"interrupted: progress saved to {ckpt}; continue with --resume")
        return {"scene": scene.name, "interrupted": True, "wall_seconds": wall}
    summary = _finish(scene, prob, sim, done, starts, out, wall)
    ckpt.unlink(missing_ok=True)
    if render:
        from .render_run import render_run

        render_run(out, emit=emit)
    emit(f"loss {summary['loss_initial']:.6e} -> {summary['loss_final']:.6e}, iou {summary['iou']:.3f}, "
         f"mass outside target {summary['mass_outside_target']:.3f}, {wall:.1f} s; results in {out}")
    return summary


def _finish(scene, prob, sim, done, starts, out, wall):
    cfg = scene.sim
    final = starts[-1] if scene.optimize.method == "positions" else sim.state(cfg.steps)
    final_x = done[-1].positions if done[-1].positions is not None else final["x"]
    finest = int(np.argmax(scene.loss.grids))
    res = scene.loss.grids[finest]
    target = prob.target_mass_grids[finest]
    mass = splat_grid(final_x, cfg.m_p, res)
    rest = problems.rest_node_mass(cfg, res)
    losses = [L for r in done for L in r.losses]
    summary = {
        "scene": scene.name,
        "loss_initial": done[0].losses[0],
        "loss_final": done[-1].losses[-1],
        "iou": problems.iou(problems.occupied(mass, rest), problems.occupied(target, rest)),
        "mass_outside_target": problems.mass_outside(mass, target),
        "iterations": sum(r.iterations for r in done),
        "converged": all(r.converged for r in done),
        "stop_reason": [r.reason for r in done],
        "wall_seconds": wall,
        "particles": len(prob.x0),
        "backend": runtime.running_arch(),  # what Taichi ran on: "cpu", "cuda" or "vulkan"
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
    if prob.target_x is not None:
        arrays["target_x"] = prob.target_x
    if prob.target_points is not None:
        arrays["target_points"] = prob.target_points
        arrays["target_colors"] = prob.target_colors
    save_npz(out / "result.npz", {"summary": {k: v for k, v in summary.items() if k != "settings"},
                                  "settings": summary["settings"], "method": scene.optimize.method}, arrays)
    save_json(out / "summary.json", summary)
    return summary


def _save_checkpoint(path, scene, done, starts, opt_state, elapsed):
    meta = {"fingerprint": fingerprint(scene), "elapsed": elapsed,
            "rounds": [{"losses": r.losses, "iterations": r.iterations, "converged": r.converged,
                        "reason": r.reason, "grad_norms": r.grad_norms} for r in done]}
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


def _load_checkpoint(path, scene):
    from .optimize import OptimizeResult

    meta, arrays = load_npz(path, "checkpoint")
    if meta.get("fingerprint") != fingerprint(scene):
        raise CheckpointError(f"{path}: made with other scene settings; drop --resume to start over, or use "
                              "the settings it was made with")
    done = [OptimizeResult(arrays[f"round_controls_{i}"], r["losses"], r["iterations"], r["converged"], r["reason"],
                           r["grad_norms"], arrays.get(f"round_positions_{i}"))
            for i, r in enumerate(meta["rounds"])]
    n_starts = len(arrays["start_x"])
    starts = [{k: arrays[f"start_{k}"][i] for k in STATE_KEYS} for i in range(n_starts)]
    opt_state = None
    if "opt" in meta:
        opt_state = dict(meta["opt"])
        opt_state.update({k[4:]: v for k, v in arrays.items() if k.startswith("opt_")})
    return done, starts, opt_state, float(meta.get("elapsed", 0.0))
