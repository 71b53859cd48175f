"""`run_scene` (mls_mpm/run.py): summary.json and result.npz hold consistent, sensible values; a run interrupted
through should_stop and continued with resume=True ends bit for bit where an uninterrupted run ends; extension
rounds (thesis 7.4) chain their initial states and frames.

Scene: tests/data/tiny.toml (32 x 32 grid, ~300 particles, 20 steps, stride 5, K = 4 controls). Every run_scene
builds its own Simulator (a couple of seconds with Taichi's offline cache warm), so runs are shared per module.
"""
import json
from pathlib import Path

import numpy as np
import pytest
import taichi as ti
from PIL import Image

from mls_mpm import SimConfig, config, problem, runtime
from mls_mpm.checkpoint import load_npz
from mls_mpm.frames import frame_paths
from mls_mpm.images import splat_grid
from mls_mpm.render import Renderer
from mls_mpm.run import run_scene
from mls_mpm.scene import load_scene
from mls_mpm.simulator import Simulator

from conftest import StopAt

TINY = Path(__file__).resolve().parent / "data" / "tiny.toml"
BASE = ["optimize.iterations=3", "optimize.tol=0.0", "sim.schedule=serial"]  # serial: a bit-identical replay
SUMMARY_KEYS = {"scene", "loss_initial", "loss_final", "iou", "mass_outside_target", "mass_error", "iterations",
                "converged", "wall_seconds", "settings"}


def quiet(*_):
    pass


def fresh_taichi():
    """Restart Taichi (CPU, float64, as conftest.py sets it) before building a Simulator or a Renderer.

    Taichi's offline cache only serves the fields of a fresh runtime: each further Simulator in one process
    recompiles its reverse kernels (~10 s of CPU), a fresh runtime loads them from the cache (~2 s). run_scene
    builds its own Simulator, as each `mls-mpm run` process does, so every run here starts a fresh runtime too;
    nothing Taichi-backed outlives a test of this module.
    """
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


def run(scene, out, **kwargs):
    fresh_taichi()
    return run_scene(scene, out, emit=quiet, **kwargs)


def scene_of(*overrides):
    return load_scene(TINY, [*BASE, *overrides])


def result(out):
    return load_npz(Path(out) / "result.npz", "result")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Uninterrupted reference runs, by optimizer, made on first use: (scene, summary, out folder)."""
    made = {}

    def get(method):
        if method not in made:
            scene = scene_of(f"optimize.method={method}", *(["optimize.lr=0.05"] if method == "adam" else []))
            out = tmp_path_factory.mktemp(f"whole_{method}")
            made[method] = (scene, run(scene, out, render=False), out)
        return made[method]

    return get


# ---------------------------------------------------------------------------------------------------------
# summary.json and result.npz

def test_summary_has_sensible_values(runs):
    scene, summary, out = runs("gd")
    assert SUMMARY_KEYS <= set(summary)
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))  # the file holds what run_scene returned
    meta, arrays = result(out)
    assert summary["scene"] == "tiny"
    assert summary["loss_initial"] == arrays["losses"][0] and summary["loss_final"] == arrays["losses"][-1]
    # gd, normalized, lr 0.1, 3 temporal iterations: 2.03e-2 -> 9.1e-3 on tiny.toml
    assert summary["loss_final"] < 0.6 * summary["loss_initial"]
    assert summary["iterations"] == 3 and summary["converged"] is False
    assert summary["stop_reason"] == ["iteration budget"]
    assert summary["settings"] == scene.to_dict() and summary["settings"]["optimize"]["iterations"] == 3
    assert 0.0 < summary["wall_seconds"] < 600.0
    assert 0.0 <= summary["mass_outside_target"] <= 1.0
    assert 0.0 <= summary["mass_error"] <= 1.0
    assert "color_error" not in summary  # colour scenes only


def test_summary_color_error_is_that_of_the_final_colours(tmp_path):
    """A colour run's color_error is the largest per-channel mass_error of the final colour-mass grid against
    the target's (problem.color_error), recomputed here from result.npz; it lies in [0, 1]."""
    images = Path(__file__).resolve().parents[1] / "scenes" / "images"
    scene = scene_of(f"scene.initial={json.dumps(str(images / 'color_halves.png'))}",
                     f"scene.target={json.dumps(str(images / 'color_swap_target.png'))}", "loss.kind=color",
                     "optimize.iterations=1")
    summary = run(scene, tmp_path / "color", render=False)
    _, arrays = result(tmp_path / "color")
    res, cfg = scene.loss.grids[0], scene.sim
    m_t = cfg.m_p * len(arrays["final_x"]) / len(arrays["target_points"])  # target_density "match"
    final = splat_grid(arrays["final_x"], cfg.m_p, res, arrays["colors"])
    target = splat_grid(arrays["target_points"], m_t, res, arrays["target_colors"])
    expected = max(0.5 * np.abs(final[..., c] - target[..., c]).sum() / target[..., c].sum() for c in range(3)
                   if target[..., c].sum() > 0)
    assert summary["color_error"] == pytest.approx(expected, rel=1e-12)
    assert 0.2 < summary["color_error"] <= 1.0  # swapped halves: far from the target after one iteration


def test_summary_iou_is_that_of_the_final_shape(runs):
    """iou and mass_outside_target measure the final particles against the target on the loss grid."""
    scene, summary, out = runs("gd")
    _, arrays = result(out)
    cfg, res = scene.sim, scene.loss.grids[0]
    rest = problem.rest_node_mass(cfg, res)
    target = problem.occupied(arrays["target_grid"], rest)

    def iou_of(x):
        return problem.iou(problem.occupied(splat_grid(x, cfg.m_p, res), rest), target)

    assert 0.0 <= summary["iou"] <= 1.0
    assert summary["iou"] == iou_of(arrays["final_x"])
    assert iou_of(arrays["init_x"][0]) != summary["iou"]  # (the initial shape scores differently: 0.86 vs 0.81)
    assert summary["mass_outside_target"] == problem.mass_outside(splat_grid(arrays["final_x"], cfg.m_p, res),
                                                                  arrays["target_grid"])
    assert summary["mass_error"] == problem.mass_error(splat_grid(arrays["final_x"], cfg.m_p, res),
                                                       arrays["target_grid"])


def test_result_replays_to_the_reported_loss(runs):
    """result.npz's controls, re-simulated from its initial state, give its final positions and final loss."""
    scene, summary, out = runs("gd")
    meta, arrays = result(out)
    prob = problem.build(scene)
    N, K = len(prob.x0), scene.sim.n_controls
    assert arrays["controls"].shape == (1, K, N, 2, 2)
    assert arrays["round_lengths"].tolist() == [4] and len(arrays["losses"]) == 4
    assert np.array_equal(arrays["init_x"][0], prob.x0)
    assert meta["method"] == "gd" and meta["settings"] == scene.to_dict()
    fresh_taichi()
    sim = Simulator(scene.sim, prob.x0, loss=prob.loss)
    assert sim.forward(arrays["controls"][0]) == summary["loss_final"]
    assert np.array_equal(sim.state(scene.sim.steps)["x"], arrays["final_x"])
    assert not (out / "checkpoint.npz").exists(), "a finished run keeps no checkpoint"


def test_positions_run(tmp_path):
    """The thesis 8.1 study: final positions optimized directly, controls left at zero."""
    scene = scene_of("optimize.method=positions")
    summary = run(scene, tmp_path, render=False)
    _, arrays = result(tmp_path)
    assert summary["iterations"] == 3 and len(arrays["losses"]) == 4
    assert summary["loss_final"] < 0.6 * summary["loss_initial"]  # measured 0.44
    assert not np.any(arrays["controls"])
    assert not np.array_equal(arrays["final_x"], arrays["init_x"][0])


# ---------------------------------------------------------------------------------------------------------
# Interrupt (should_stop) and resume

def interrupt(scene, out, n):
    summary = run(scene, out, should_stop=StopAt(n), render=False)
    assert summary["interrupted"] is True
    assert (out / "checkpoint.npz").is_file()
    assert not (out / "result.npz").exists() and not (out / "summary.json").exists(), "an interrupted run wrote results"
    return load_npz(out / "checkpoint.npz", "checkpoint")[0]


def assert_same_run(out, reference_out):
    meta, arrays = result(out)
    ref_meta, ref = result(reference_out)
    assert np.array_equal(arrays["losses"], ref["losses"]), (arrays["losses"], ref["losses"])
    assert np.array_equal(arrays["controls"], ref["controls"])
    assert np.array_equal(arrays["final_x"], ref["final_x"])
    assert np.array_equal(arrays["round_lengths"], ref["round_lengths"])
    drop = ("wall_seconds",)
    assert {k: v for k, v in meta["summary"].items() if k not in drop} == \
           {k: v for k, v in ref_meta["summary"].items() if k not in drop}
    assert not (out / "checkpoint.npz").exists()


K_BOUNDARY_BUG = ("bug: gd interrupted after the last control step of a temporal iteration checkpoints k = K; "
                  "resumed, it ends that iteration as 'gradient norm below tolerance' and stops early "
                  "(optimize.py gd: keep `small` in the checkpointed state like `improved`)")


@pytest.mark.parametrize("method,n", [
    ("gd", 2),  # mid temporal iteration 1
    ("gd", 4),  # after its last control (k = K checkpointed)
    ("gd", 5),  # between temporal iterations 1 and 2
    ("adam", 2),
    ("lbfgs", 2),
])
def test_resume_equals_uninterrupted(runs, tmp_path, method, n):
    scene, _, whole = runs(method)
    meta = interrupt(scene, tmp_path, n)
    assert meta["opt"]["iteration"] == (n // 5 if method == "gd" else n)
    summary = run(scene, tmp_path, resume=True, render=False)
    assert "interrupted" not in summary
    assert_same_run(tmp_path, whole)


def test_resume_equals_uninterrupted_parallel_schedule(tmp_path_factory):
    """The parallel schedule (private grids per thread) must replay bit for bit too."""
    scene = scene_of("optimize.method=lbfgs", "sim.schedule=parallel", "sim.threads=2")
    whole, part = tmp_path_factory.mktemp("whole_parallel"), tmp_path_factory.mktemp("part_parallel")
    run(scene, whole, render=False)
    interrupt(scene, part, 1)
    run(scene, part, resume=True, render=False)
    assert_same_run(part, whole)


def test_resume_keeps_the_schedule_auto_chose(tmp_path_factory, monkeypatch):
    """Under sim.schedule = "auto" a resumed process can resolve the other schedule (2D on 2 CPUs follows whether
    mls_mpm/affinity.py's probe pinned the workers, which can fail on a loaded machine): the resume steps in the
    schedule its checkpoint names and ends bit for bit where the uninterrupted run ends. auto is made to pick one or
    the other through its thresholds (config.SERIAL_BELOW*): parallel for the uninterrupted and the interrupted run,
    serial for the resume."""
    scene = scene_of("optimize.method=lbfgs", "sim.schedule=auto", "sim.threads=2")

    def auto_picks(schedule):
        below = 0 if schedule == "parallel" else 10 ** 9
        for name in ("SERIAL_BELOW", "SERIAL_BELOW_2D_TWO_THREADS", "SERIAL_BELOW_2D_PINNED"):
            monkeypatch.setattr(config, name, below)

    whole, part, serial = (tmp_path_factory.mktemp(n) for n in ("whole_auto", "part_auto", "serial_auto"))
    auto_picks("serial")
    assert run(scene, serial, render=False)["schedule"] == "serial"
    auto_picks("parallel")
    assert run(scene, whole, render=False)["schedule"] == "parallel"
    # what the resume must not do: the two schedules' runs differ in round-off
    assert not np.array_equal(result(serial)[1]["losses"], result(whole)[1]["losses"])
    interrupt(scene, part, 1)
    auto_picks("serial")
    lines = []
    fresh_taichi()
    summary = run_scene(scene, part, resume=True, render=False, emit=lines.append)
    assert summary["schedule"] == "parallel"
    assert any(line.endswith("(parallel schedule)") for line in lines), lines
    assert_same_run(part, whole)


def test_resume_when_every_round_is_done(runs, tmp_path, monkeypatch):
    """A run killed after its last checkpoint (every round done) but before its result: the resume re-simulates
    the last round for the final state instead of reading a Simulator that never ran."""
    import mls_mpm.run as run_module

    scene, _, whole = runs("lbfgs")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(run_module, "_finish", killed)
        with pytest.raises(KeyboardInterrupt):
            run(scene, tmp_path, render=False)
    meta, _ = load_npz(tmp_path / "checkpoint.npz", "checkpoint")
    assert len(meta["rounds"]) == 1 and "opt" not in meta
    lines = []
    fresh_taichi()
    run_scene(scene, tmp_path, resume=True, render=False, emit=lines.append)
    assert any("every round is done" in line for line in lines), lines
    assert_same_run(tmp_path, whole)


def test_zero_iterations_give_the_initial_controls(tmp_path):
    """optimize.iterations = 0 (lbfgs raised IndexError and left a checkpoint): the result holds the initial
    controls and loss, stopped by the iteration budget."""
    summary = run(scene_of("optimize.method=lbfgs", "optimize.iterations=0"), tmp_path, render=False)
    _, arrays = result(tmp_path)
    assert summary["iterations"] == 0 and summary["stop_reason"] == ["iteration budget"]
    assert summary["loss_final"] == summary["loss_initial"] and arrays["losses"].tolist() == [summary["loss_initial"]]
    assert not np.any(arrays["controls"]) and not (tmp_path / "checkpoint.npz").exists()


def test_resume_allows_a_larger_iteration_budget(runs, tmp_path):
    """The iteration budget is not part of the checkpoint's fingerprint: a run stopped in iteration 1 of 2 and
    resumed with a budget of 3 ends where a 3-iteration run ends."""
    _, _, whole = runs("gd")
    interrupt(scene_of("optimize.iterations=2"), tmp_path, 2)
    run(scene_of(), tmp_path, resume=True, render=False)
    assert_same_run(tmp_path, whole)


# ---------------------------------------------------------------------------------------------------------
# Extension rounds (thesis 7.4)

ROUNDS = ["optimize.rounds=2", "optimize.iterations=2"]


@pytest.fixture(scope="module")
def two_rounds(tmp_path_factory):
    scene = scene_of(*ROUNDS)
    out = tmp_path_factory.mktemp("rounds")
    return scene, run(scene, out, render=True), out


def test_rounds_chain_their_initial_states(two_rounds):
    scene, summary, out = two_rounds
    _, arrays = result(out)
    prob = problem.build(scene)
    N, K, T = len(prob.x0), scene.sim.n_controls, scene.sim.steps
    assert arrays["controls"].shape == (2, K, N, 2, 2)
    assert arrays["round_lengths"].tolist() == [3, 3] and summary["iterations"] == 4
    assert summary["stop_reason"] == ["iteration budget", "iteration budget"]
    assert np.array_equal(arrays["init_x"][0], prob.x0)
    fresh_taichi()
    sim = Simulator(scene.sim, prob.x0, loss=prob.loss)
    sim.forward(arrays["controls"][0])
    end_of_first = sim.state(T)
    assert np.array_equal(arrays["init_x"][1], end_of_first["x"]), "round 2 must start where round 1 ended"
    # carry_state = false: round 2 starts at rest, undeformed
    assert not np.any(arrays["init_v"][1]) and not np.any(arrays["init_C"][1])
    assert np.array_equal(arrays["init_F"][1], np.tile(np.eye(2), (N, 1, 1)))
    sim.set_initial(arrays["init_x"][1])
    assert sim.forward(arrays["controls"][1]) == summary["loss_final"]
    assert np.array_equal(sim.state(T)["x"], arrays["final_x"])
    # round 2 starts from round 1's end, so it starts nearer the target than round 1 did
    assert arrays["losses"][3] < arrays["losses"][0]


def test_round_frames_are_in_sequence(two_rounds):
    """Frames every 5 of 20 steps: 5 for round 1, then 4 for round 2 (its step 0 is round 1's last frame)."""
    scene, summary, out = two_rounds
    _, arrays = result(out)
    paths = frame_paths(out / "frames")
    assert [p.name for p in paths] == [f"frame_{i:05d}.png" for i in range(9)]
    cfg = scene.sim
    fresh_taichi()
    renderer = Renderer(cfg.n_grid, len(arrays["final_x"]), size=scene.render.size,
                        rest_node_mass=cfg.density * cfg.dx ** 2, mode="mass")

    def frame(i):
        return np.asarray(Image.open(paths[i]).convert("RGB"))

    def drawn(x):
        return renderer.render(x, cfg.m_p, colors=arrays["colors"])

    assert np.array_equal(frame(0), drawn(arrays["init_x"][0]))
    assert np.array_equal(frame(4), drawn(arrays["init_x"][1]))  # round 1's end = round 2's start
    assert np.array_equal(frame(8), drawn(arrays["final_x"]))
    assert not np.array_equal(frame(4), frame(8))


def test_rounds_resume_in_the_second_round(two_rounds, tmp_path):
    """Stopped in round 2 (round 1: 2 iterations x (4 + 1) should_stop calls), resumed: the same two rounds."""
    scene, _, whole = two_rounds
    meta = interrupt(scene, tmp_path, 12)
    assert len(meta["rounds"]) == 1 and meta["opt"]["k"] == 2
    run(scene, tmp_path, resume=True, render=False)
    assert_same_run(tmp_path, whole)
