"""Coarse-to-fine stages and the wall-clock budget (mls_mpm/schedule.py, Simulator.set_active_grids, optimize.schedule
and optimize.max_seconds in scenes): how iterations and time are split among stages, that a stage's loss is the
loss of its grids alone, that a staged run's result concatenates its stages and resumes bit for bit, that a run past
its budget writes its result, and the scene keys' refusals.

Scenes: conftest's small simulation (32 x 32 grid, ~290 particles, 20 steps) for the loss of a stage, and
tests/data/tiny.toml (32 x 32, ~300 particles, 20 steps, K = 4) with loss grids [16, 32] and the stages [16] then
[16, 32] for the runs. The deadlines are checked with a fake clock on `staged` around a fake optimizer (no
simulation).
"""
import json
import re
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

import mls_mpm
from conftest import StopAt, blob, random_controls, rel_err, scene_config
from mls_mpm import SimConfig, problem, runtime
from mls_mpm.checkpoint import load_npz, save_npz
from mls_mpm.optimize import OptimizeResult
from mls_mpm.run import run_scene
from mls_mpm.scene import SceneError, load_scene
from mls_mpm.schedule import BUDGET_REASON, Stage, stage_iterations, staged
from mls_mpm.simulator import Simulator

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.toml"
SCHEDULE = "optimize.schedule=[{grids = [16], share = 2}, {grids = [16, 32], share = 1}]"
STAGED = ["loss.grids=[16, 32]", SCHEDULE, "optimize.method=lbfgs", "optimize.iterations=3", "optimize.tol=0.0",
          "sim.schedule=serial"]  # serial: a bit-identical replay; iterations 3 -> stages of 2 and 1
ROUNDOFF = 1e-12


def quiet(*_):
    pass


# ---------------------------------------------------------------------------------------------------------
# stage_iterations

@pytest.mark.parametrize("total, shares, want", [
    (30, [1, 2], [10, 20]),
    (10, [1, 1, 1], [3, 4, 3]),
    (80, [1.0, 2.0], [27, 53]),
    (8, [0.5, 0.25, 0.25], [4, 2, 2]),
    (7, [0.5, 0.25, 0.25], [4, 1, 2]),  # cumulative rounding: each within one of the exact 3.5, 1.75, 1.75
    (1, [1, 2], [0, 1]),
    (2, [1, 1, 1], [1, 0, 1]),
    (0, [1, 2], [0, 0]),
    (5, [3], [5]),
])
def test_stage_iterations_split_in_proportion_and_sum_exactly(total, shares, want):
    counts = stage_iterations(total, shares)
    assert counts == want
    assert sum(counts) == total and all(c >= 0 for c in counts)


def test_stage_iterations_are_within_one_of_the_exact_share():
    rng = np.random.default_rng(0)
    for _ in range(200):
        shares = list(rng.uniform(0.1, 5.0, rng.integers(1, 6)))
        total = int(rng.integers(0, 300))
        counts = stage_iterations(total, shares)
        assert sum(counts) == total and all(c >= 0 for c in counts)
        exact = total * np.array(shares) / sum(shares)
        assert np.all(np.abs(np.array(counts) - exact) < 1.0 + 1e-9), (total, shares, counts)


# ---------------------------------------------------------------------------------------------------------
# Simulator.set_active_grids: the loss of a stage is that of its grids alone

def disk_mass(res, center=(0.53, 0.47), radius=0.13):
    h = 1.0 / res
    i, j = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    return h * h * np.clip((radius - np.hypot(i * h - center[0], j * h - center[1])) / h + 0.5, 0.0, 1.0)


@pytest.fixture(scope="module")
def two_grid_sims():
    """A simulator whose mass loss has a 32 and a 16 grid (weights 1 and 0.5), one with only the 16 grid's term,
    and controls (20 steps, stride 10: K = 2)."""
    cfg = scene_config(steps=20)
    x0 = blob()
    both = Simulator(cfg, x0, loss=mls_mpm.MassLoss([disk_mass(32), disk_mass(16)], weights=[1.0, 0.5]))
    alone = Simulator(cfg, x0, loss=mls_mpm.MassLoss([disk_mass(16)], weights=[0.5]))
    return both, alone, random_controls(both.control_shape, 0.05, seed=3)


def test_active_grids_give_the_loss_and_gradient_of_those_grids_alone(two_grid_sims):
    both, alone, c = two_grid_sims
    L_alone = alone.forward(c)
    g_alone = alone.backward()
    both.set_active_grids([16])
    L16 = both.forward(c)
    assert abs(L16 - L_alone) <= ROUNDOFF * abs(L_alone)
    assert rel_err(both.backward(), g_alone) <= ROUNDOFF
    both.set_active_grids([32])
    L32 = both.forward(c)
    g32 = both.backward()
    both.set_active_grids(None)  # every grid again: the sum of the two terms
    L = both.forward(c)
    assert L > L16 > 0 and L32 > 0
    assert abs(L - (L16 + L32)) <= ROUNDOFF * L
    assert rel_err(both.backward(), g_alone + g32) <= 1e-10
    both.set_active_grids([16, 32])
    assert both.forward(c) == L


def test_active_grids_refuse_an_unknown_resolution(two_grid_sims):
    both, _, c = two_grid_sims
    L = both.forward(c)
    with pytest.raises(ValueError, match=r"\[24\]"):
        both.set_active_grids([16, 24])
    assert both.forward(c) == L  # the refusal changed nothing


# ---------------------------------------------------------------------------------------------------------
# staged() around a fake optimizer and a fake clock: what it concatenates, and its deadlines

class Clock:
    def __init__(self, t=1000.0):
        self.t = t

    def __call__(self):
        return self.t


class FakeSim:
    """A loss of 10 per active grid plus the controls' value; records the active grids of each forward."""

    GRIDS = (16, 32)

    def __init__(self):
        self.active, self.log = self.GRIDS, []

    def set_active_grids(self, resolutions=None):
        self.active = self.GRIDS if resolutions is None else tuple(resolutions)

    def forward(self, c):
        self.log.append(self.active)
        return 10.0 * len(self.active) + float(c)

    def backward(self):
        """dL/dc of the last forward (staged compiles the kernels with one forward and backward under a budget)."""
        return 1.0


def fake_method(clock, seconds_per_iteration, starts):
    """An optimizer that lowers the controls by 1 per iteration, taking seconds_per_iteration of the fake clock;
    it checks should_stop after each iteration, as the real ones do. starts: (clock, iterations) of each call."""

    def method(sim, controls, settings, on_checkpoint=None, should_stop=None, emit=print, resume=None):
        starts.append((clock(), settings.iterations))
        c, losses = controls, [sim.forward(controls)]
        for i in range(settings.iterations):
            clock.t += seconds_per_iteration
            c = c - 1.0
            losses.append(sim.forward(c))
            if should_stop and should_stop():
                return OptimizeResult(c, losses, i + 1, False, "interrupted", [1.0] * (i + 1))
        return OptimizeResult(c, losses, settings.iterations, True, "iteration budget", [1.0] * settings.iterations)

    return method


def settings(iterations):
    return load_scene(TINY, [f"optimize.iterations={iterations}"]).optimize


def test_staged_concatenates_the_stages():
    clock, starts, lines = Clock(), [], []
    sim = FakeSim()
    run = staged(fake_method(clock, 1.0, starts), [Stage((16,), 1.0), Stage((16, 32), 2.0)], clock=clock)
    res = run(sim, 0.0, settings(6), emit=lines.append)
    assert [n for _, n in starts] == [2, 4]
    # stage 1: 10 - c on one grid from c = 0; stage 2: 20 - c on both from c = -2
    assert res.losses == [10.0, 9.0, 8.0, 18.0, 17.0, 16.0, 15.0, 14.0]
    assert res.iterations == 6 and res.controls == -6.0 and res.grad_norms == [1.0] * 6
    assert res.loss_start == 20.0  # the last stage's loss of the starting controls
    assert res.reason == "iteration budget"
    assert res.restarted == []  # stage 1 lowered both grids' loss: kept
    assert sim.active == (16, 32)  # every grid again afterwards
    assert [line.split(":")[0] for line in lines] == ["stage 1/2", "stage 2/2"]


class TearingSim(FakeSim):
    """Grid 16's loss falls as the controls fall (10 + c), grid 32's rises three times as fast (10 - 3 c): lowering
    the coarse loss alone raises the loss of both, as a coarse stage that tears the body into blobs."""

    def forward(self, c):
        self.log.append(self.active)
        return (10.0 + float(c) if 16 in self.active else 0.0) + (10.0 - 3.0 * float(c) if 32 in self.active else 0.0)


def test_a_stage_that_raises_the_measured_loss_hands_on_the_starting_controls():
    """Stage 1 lowers grid 16's loss to 8 (c = -2) but leaves both grids' at 24, above their 20 at c = 0: stage 2
    starts from c = 0 (its first loss is 20, not 24), and the run says so; where stage 1 lowers both grids' loss
    (FakeSim, test_staged_concatenates_the_stages) it starts from stage 1's controls."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 1.0, starts), [Stage((16,), 1.0), Stage((16, 32), 2.0)], clock=clock)
    res = run(TearingSim(), 0.0, settings(6), emit=lines.append)
    assert res.losses[:3] == [10.0, 9.0, 8.0]
    assert res.losses[3] == 20.0 == res.loss_start  # stage 2 from the starting controls
    assert res.controls == -4.0  # its 4 iterations from 0
    assert res.restarted == [1]  # and the result says so (summary.json's stages_restarted)
    assert any(line.startswith("stage 1/2 left the loss of grids [16, 32] at 2.400000e+01, above its 2.000000e+01")
               for line in lines), lines


def test_a_resumed_run_keeps_the_stages_set_aside_before_it():
    """Resumed in stage 2 of 2 from a checkpoint whose stage 1 was set aside (STAGE_STATE's stage_restarts = [1]):
    the result still lists stage 1, and stage 2's own decision adds nothing (the last stage has none)."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 1.0, starts), [Stage((16,), 1.0), Stage((16, 32), 2.0)], clock=clock)
    resume = {"controls": 0.0, "stage": 1, "stage_losses": [10.0, 9.0, 8.0], "stage_grad_norms": [1.0, 1.0],
              "stage_iterations": 2, "loss_start": 20.0, "stage_restarts": [1]}
    res = run(TearingSim(), 0.0, settings(6), emit=lines.append, resume=resume)
    assert [n for _, n in starts] == [4]  # stage 2 alone
    assert res.restarted == [1] and res.iterations == 6 and res.losses[:3] == [10.0, 9.0, 8.0]


def test_out_of_time_in_a_stage_that_raised_the_measured_loss_ends_with_the_starting_controls():
    """The budget runs out in stage 1 of 2 after it raised both grids' loss: the run ends with the starting controls
    and their loss, not stage 1's worse ones."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 100.0, starts), [Stage((16,), 1.0), Stage((16, 32), 1.0)], max_seconds=50.0,
                 clock=clock)
    res = run(TearingSim(), 0.0, settings(10), emit=lines.append)
    assert res.controls == 0.0 and res.losses[-1] == 20.0 == res.loss_start
    assert res.reason == BUDGET_REASON and res.restarted == [1]


def test_one_stage_is_the_plain_optimizer():
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 1.0, starts), [Stage((16, 32), 1.0)], clock=clock)
    res = run(FakeSim(), 0.0, settings(3), emit=lines.append)
    assert res.losses == [20.0, 19.0, 18.0, 17.0] and res.iterations == 3 and res.loss_start == 20.0
    assert lines == [] and len(starts) == 1


def stage_seconds(lines):
    return [float(re.search(r", (\d+) s$", line).group(1)) for line in lines]


def test_stage_deadlines_split_the_time_left_by_share():
    """300 s, shares 1 and 2: stage 1 gets 100 s. At 30 s an iteration, stage 1's 10 iterations would take 300 s:
    it stops after 4 (120 s, past its 100 s) and stage 2 gets the 180 s left, where 6 iterations end it."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 30.0, starts), [Stage((16,), 1.0), Stage((16, 32), 2.0)], max_seconds=300.0,
                 clock=clock)
    res = run(FakeSim(), 0.0, settings(30), emit=lines.append)
    assert stage_seconds(lines) == [100.0, 180.0]
    assert [n for _, n in starts] == [10, 20]
    assert res.iterations == 4 + 6 and clock.t == 1000.0 + 300.0
    assert res.reason == BUDGET_REASON and res.converged is False
    assert len(res.losses) == (1 + 4) + (1 + 6)


class CompilingSim(FakeSim):
    """A FakeSim whose first backward takes `compile_seconds` of the clock, like Taichi compiling the kernels."""

    def __init__(self, clock, compile_seconds):
        super().__init__()
        self.clock, self.compile_seconds, self.compiled = clock, compile_seconds, False

    def backward(self):
        if not self.compiled:
            self.clock.t += self.compile_seconds
            self.compiled = True
        return 1.0


def test_the_kernels_compile_before_the_stage_clocks_start():
    """300 s with 60 s of compilation: the stages split the 240 s left after it (stage 1 gets 80 s by shares 1, 2,
    not 100 s less the compilation); stage 1's 2 iterations of 1 s leave the last stage 238 s."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 1.0, starts), [Stage((16,), 1.0), Stage((16, 32), 2.0)], max_seconds=300.0,
                 clock=clock)
    run(CompilingSim(clock, 60.0), 0.0, settings(6), emit=lines.append)
    assert stage_seconds(lines) == [80.0, 238.0]


def test_a_stage_finishing_early_leaves_its_time_to_the_next():
    """Stage 1 of 3 (shares 1, 1, 2) gets 100 of 400 s and uses 20; stage 2 then gets 380 * 1/3, stage 3 the rest."""
    clock, starts, lines = Clock(), [], []
    stages = [Stage((16,), 1.0), Stage((32,), 1.0), Stage((16, 32), 2.0)]
    run = staged(fake_method(clock, 10.0, starts), stages, max_seconds=400.0, clock=clock)
    res = run(FakeSim(), 0.0, settings(8), emit=lines.append)  # 2, 2 and 4 iterations of 10 s
    assert stage_seconds(lines) == [100.0, round(380.0 / 3), 360.0]
    assert res.reason == "iteration budget" and res.iterations == 8


def test_started_counts_time_already_spent():
    """A resumed run passes started = now - elapsed: 250 of 300 s spent leaves 50 s, 25 s to stage 1 of two equal
    ones."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 1.0, starts), [Stage((16,), 1.0), Stage((16, 32), 1.0)], max_seconds=300.0,
                 started=clock() - 250.0, clock=clock)
    run(FakeSim(), 0.0, settings(4), emit=lines.append)
    assert stage_seconds(lines) == [25.0, 48.0]  # stage 2: the 48 s stage 1 left


def test_a_budget_spent_in_stage_one_ends_the_run():
    """Past the whole deadline in stage 1: no stage 2; the result is stage 1's controls, with the budget's reason."""
    clock, starts, lines = Clock(), [], []
    run = staged(fake_method(clock, 100.0, starts), [Stage((16,), 1.0), Stage((16, 32), 1.0)], max_seconds=50.0,
                 clock=clock)
    sim = FakeSim()
    res = run(sim, 0.0, settings(10), emit=lines.append)
    assert len(starts) == 1 and res.iterations == 1 and res.controls == -1.0
    # stage 1's losses, then the last stage's loss of the controls the run ends with: loss_final is measured
    # like loss_start (20), on every grid
    assert res.losses == [10.0, 9.0, 19.0] and res.loss_start == 20.0
    assert res.reason == BUDGET_REASON and res.converged is False
    assert sim.active == (16, 32)


# ---------------------------------------------------------------------------------------------------------
# Staged runs through run_scene

def fresh_taichi():
    """A fresh Taichi runtime before each run_scene (its reverse kernels then load from the offline cache; see
    tests/test_run.py)."""
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


def run(scene, out, **kwargs):
    fresh_taichi()
    return run_scene(scene, out, emit=quiet, render=False, **kwargs)


def scene_of(*overrides):
    return load_scene(TINY, [*STAGED, *overrides])


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    """The uninterrupted staged lbfgs run: (scene, summary, result arrays)."""
    scene = scene_of()
    out = tmp_path_factory.mktemp("whole")
    summary = run(scene, out)
    return scene, summary, load_npz(out / "result.npz", "result")[1]


def full_loss(scene, controls):
    """The loss of every grid (the last stage's) of these controls from the scene's initial state."""
    prob = problem.build(scene)
    fresh_taichi()
    sim = Simulator(scene.sim, prob.x0, loss=prob.loss)
    return sim, sim.forward(controls)


def test_a_staged_run_concatenates_its_stages(whole):
    scene, summary, arrays = whole
    assert summary["iterations"] == 3 and summary["stop_reason"] == ["iteration budget"]
    losses = arrays["losses"]
    assert len(losses) == (1 + 2) + (1 + 1) and arrays["round_lengths"].tolist() == [5]
    assert summary["loss_final"] == losses[-1]
    assert losses[2] < losses[1] < losses[0] and losses[4] < losses[3]  # each stage lowers its own loss
    sim, L_final = full_loss(scene, arrays["controls"][0])
    assert L_final == summary["loss_final"]
    L_zero = sim.forward(sim.zero_controls())
    assert summary["loss_initial"] == L_zero  # every grid's loss of zero controls, not stage 1's
    sim.set_active_grids([16])
    assert sim.forward(sim.zero_controls()) == losses[0]  # stage 1 starts with the 16 grid's loss alone
    assert losses[0] < L_zero


@pytest.mark.parametrize("n", [1, 2, 3], ids=["in_stage_1", "at_the_end_of_stage_1", "at_the_end_of_stage_2"])
def test_an_interrupted_staged_run_resumes_bit_for_bit(whole, tmp_path, n):
    """Stopped after n lbfgs iterations (stage 1 has 2, stage 2 has 1), then resumed: the same controls and
    losses, ==, as the uninterrupted run."""
    scene, summary, arrays = whole
    stopped = run(scene, tmp_path, should_stop=StopAt(n))
    assert stopped["interrupted"] and (tmp_path / "checkpoint.npz").exists()
    meta, _ = load_npz(tmp_path / "checkpoint.npz", "checkpoint")
    assert meta["opt"]["stage"] == (0 if n <= 2 else 1)
    resumed = run(scene, tmp_path, resume=True)
    _, again = load_npz(tmp_path / "result.npz", "result")
    assert np.array_equal(again["controls"], arrays["controls"])
    assert again["losses"].tolist() == arrays["losses"].tolist()
    for key in ("loss_initial", "loss_final", "iou", "iterations", "stop_reason", "stages_restarted", "mass_error"):
        assert resumed[key] == summary[key], key


def test_a_checkpoint_without_the_set_aside_stages_resumes(whole, tmp_path):
    """A checkpoint of an earlier version, which had no `stage_restarts` (STAGE_STATE) or per-round `restarted`:
    resumed as one in which no stage was set aside, to the uninterrupted run's result (interrupted after stage 1's
    two iterations, so that the checkpoint holds the stage state)."""
    scene, summary, arrays = whole
    run(scene, tmp_path, should_stop=StopAt(2))
    path = tmp_path / "checkpoint.npz"
    meta, saved = load_npz(path, "checkpoint")
    assert meta["opt"].pop("stage_restarts") == []
    for r in meta["rounds"]:
        r.pop("restarted")
    save_npz(path, meta, saved)
    resumed = run(scene, tmp_path, resume=True)
    assert resumed["stages_restarted"] == summary["stages_restarted"] == [[]]
    _, again = load_npz(tmp_path / "result.npz", "result")
    assert np.array_equal(again["controls"], arrays["controls"])


def test_a_run_past_its_budget_writes_its_result(tmp_path):
    """max_seconds = 0.001 is spent before the first stage starts: stage 1 makes its one lbfgs iteration (an
    optimizer checks the clock after each) and the run ends there, with its result."""
    scene = scene_of("optimize.max_seconds=0.001", "optimize.iterations=3")
    summary = run(scene, tmp_path)
    assert summary["stop_reason"] == [BUDGET_REASON] and summary["converged"] is False
    assert summary["iterations"] == 1
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["stop_reason"] == [BUDGET_REASON] and on_disk["converged"] is False
    _, arrays = load_npz(tmp_path / "result.npz", "result")
    assert not (tmp_path / "checkpoint.npz").exists()
    assert np.any(arrays["controls"]) and summary["loss_final"] == arrays["losses"][-1]
    # the final loss is measured like the initial one: every grid's loss (that of the last stage)
    _, L_final = full_loss(scene, arrays["controls"][0])
    assert summary["loss_final"] == L_final


def test_later_rounds_run_the_last_stage_alone(tmp_path):
    """With rounds = 2, round 1 runs the schedule's stages and round 2 the last stage alone, with every
    iteration; interrupted in round 2 and resumed, the run ends bit for bit where the uninterrupted one does."""
    scene = scene_of("optimize.rounds=2")
    lines = []
    fresh_taichi()
    summary = run_scene(scene, tmp_path / "whole", emit=lines.append, render=False)
    second = lines.index("round 2/2")
    assert [ln for ln in lines[:second] if ln.startswith("stage ")][0].startswith("stage 1/2: loss grids [16]")
    assert not any(ln.startswith("stage ") for ln in lines[second:])
    _, arrays = load_npz(tmp_path / "whole" / "result.npz", "result")
    assert arrays["round_lengths"].tolist() == [(1 + 2) + (1 + 1), 1 + 3]  # round 2: one stage of 3 iterations
    stopped = run(scene, tmp_path / "cut", should_stop=StopAt(4))  # round 1 has 3 iterations: stop in round 2
    assert stopped["interrupted"]
    meta, _ = load_npz(tmp_path / "cut" / "checkpoint.npz", "checkpoint")
    assert len(meta["rounds"]) == 1 and "stage" not in meta["opt"]
    resumed = run(scene, tmp_path / "cut", resume=True)
    _, again = load_npz(tmp_path / "cut" / "result.npz", "result")
    assert np.array_equal(again["controls"], arrays["controls"])
    assert again["losses"].tolist() == arrays["losses"].tolist() and resumed["iou"] == summary["iou"]


def test_rounds_share_the_budget(tmp_path):
    """optimize.max_seconds with rounds = 2: the first round gets 2/3 of the budget, the second what is left
    (the first used to be able to spend it all and leave none for the second); a round stopped by its share
    of the budget is followed by the next round."""
    lines = []
    # the budget counts the kernels' compile (~1 s here, ~8 s beside another busy test process on 2 cores):
    # 20 s leaves the first round's 2/3 share room for a first iteration on a loaded machine
    budget = 20
    scene = scene_of(f"optimize.max_seconds={budget}", "optimize.iterations=100000", "optimize.rounds=2")
    fresh_taichi()
    summary = run_scene(scene, tmp_path, emit=lines.append, render=False)
    assert summary["stop_reason"] == [BUDGET_REASON, BUDGET_REASON]
    assert summary["wall_seconds"] < budget + 5  # the budget, plus the last iteration and the result
    assert any(line.startswith("round 2/2") for line in lines)
    _, arrays = load_npz(tmp_path / "result.npz", "result")
    assert arrays["controls"].shape[0] == 2 and all(n > 1 for n in arrays["round_lengths"])


# ---------------------------------------------------------------------------------------------------------
# Scene keys

def write_scene(tmp_path, optimize_lines):
    images = ROOT / "scenes" / "images"
    path = tmp_path / "s.toml"
    path.write_text(f"""
[scene]
initial = "{images / 'circle_small.png'}"
target = "{images / 'torus.png'}"

[sim]
n_grid = 32
steps = 20
dt = 0.008333333333333333
E = 88.0
density = 40.0
gravity = [0.0, 0.0]

[loss]
kind = "mass"
grids = [16, 32]

[optimize]
{optimize_lines}
""")
    return path


def test_a_schedule_loads_with_share_defaulting_to_one(tmp_path):
    scene = load_scene(write_scene(tmp_path, "schedule = [{grids = [16]}, {grids = [32, 16], share = 2.5}]\n"
                                             "max_seconds = 12"))
    assert scene.optimize.schedule == ({"grids": (16,), "share": 1.0}, {"grids": (32, 16), "share": 2.5})
    assert scene.optimize.max_seconds == 12.0
    plain = load_scene(write_scene(tmp_path, ""))
    assert plain.optimize.schedule == () and plain.optimize.max_seconds == 0.0


@pytest.mark.parametrize("line, pattern", [
    ("schedule = [{grids = [8]}]", r"optimize\.schedule = \[\{grids = \[8\]\}\]: expected stages whose grids are "
                                   r"among loss\.grids = \[16, 32\] \(stage 1 has \[8\]\)"),
    ("schedule = [{grids = [16]}, {grids = [16, 64]}]", r"optimize\.schedule = .*: expected stages whose grids are "
                                                        r"among loss\.grids = \[16, 32\] \(stage 2 has \[16, 64\]\)"),
    ("schedule = []", r"optimize\.schedule = \[\]: expected a non-empty list of stages"),
    ("schedule = [{share = 1.0}]", r"optimize\.schedule = \[\{share = 1\.0\}\]: expected a non-empty list of stages"),
    ("schedule = [{grids = []}]", r"optimize\.schedule = .*: expected a non-empty list of stages"),
    ("schedule = [{grids = [16], weight = 2}]", r"optimize\.schedule = .*weight = 2.*: expected a non-empty list"),
    ("schedule = [{grids = [16], share = 0}]", r"optimize\.schedule = .*share = 0.*: expected .*share = a number > 0"),
    ("schedule = [{grids = [16], share = -1.0}]", r"optimize\.schedule = .*: expected .*share = a number > 0"),
    ("schedule = [16, 32]", r"optimize\.schedule = \[16, 32\]: expected a non-empty list of stages"),
    ("schedule = {grids = [16]}", r"optimize\.schedule = .*: expected a non-empty list of stages"),
    ("max_seconds = -1", r"optimize\.max_seconds = -1: expected a number >= 0"),
    ("max_seconds = \"1 min\"", r"optimize\.max_seconds = \"1 min\": expected a number >= 0"),
])
def test_schedule_and_budget_refusals(tmp_path, line, pattern):
    """Each refusal is one SceneError line: `<file>: optimize.<key> = <value>: expected <what>`."""
    path = write_scene(tmp_path, line)
    with pytest.raises(SceneError) as e:
        load_scene(path)
    message = str(e.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    assert re.search(pattern, message), message


def test_checkpoint_fingerprint_ignores_the_budget_but_not_the_schedule():
    from mls_mpm.run import fingerprint

    base = scene_of()
    assert fingerprint(scene_of("optimize.max_seconds=30")) == fingerprint(base)
    other = scene_of("optimize.schedule=[{grids = [16], share = 1}, {grids = [16, 32], share = 1}]")
    assert fingerprint(other) != fingerprint(base)
