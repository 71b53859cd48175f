"""A 3D scene end to end (sim.dim = 3): `run_scene` writes result.npz and summary.json with 3D arrays and a 3D iou,
an interrupted run resumed ends bit for bit where an uninterrupted one ends, and `check` passes on it (against
the Tape, which runs in a child process in 3D, and central differences).

Scene: a ball becoming a torus on a 12^3 grid (walls 2 cells wide), ~190 particles, 12 steps, a control every 4
steps, 2 chained rounds (carry_state), L-BFGS with 2 iterations a round. 3D kernels compile slowly (minutes on a
busy 2-core machine), so every run and the check use one set of field shapes (the check keeps every particle and
its reduced scene is the scene itself: f64, 12 steps, stride 4) and each starts a fresh Taichi runtime, whose
offline cache then serves the kernels compiled by the first.
"""
import argparse
import json

import numpy as np
import pytest
import taichi as ti

from mls_mpm import SimConfig, problem, runtime
from mls_mpm.check import check_scene
from mls_mpm.checkpoint import load_npz
from mls_mpm.images import splat_grid
from mls_mpm.result import load_result
from mls_mpm.run import run_scene
from mls_mpm.scene import load_scene

from conftest import StopAt

pytestmark = pytest.mark.slow

SCENE = """[scene]
initial = "shape:sphere?r=0.45"
target = "shape:torus?R=0.3&r=0.15"

[sim]
dim = 3
n_grid = 12
bound = 2
steps = 12
dt = 0.008333333333333333
E = 16.0
nu = 0.3
density = 40.0
gamma = 0.5
gravity = [0.0, 0.0, 0.0]
particles_per_cell = 8
schedule = "serial"  # one serial launch a run: bit-identical replays

[control]
stride = 4

[loss]
kind = "mass"
grids = [6, 12]

[optimize]
method = "lbfgs"
iterations = 2
tol = 0.0
rounds = 2
carry_state = true
"""


def quiet(*_):
    pass


def fresh_taichi():
    """A fresh CPU float64 runtime before each run (see tests/test_run.py: the offline cache serves it)."""
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene3d") / "ball_to_torus_3d.toml"
    path.write_text(SCENE)
    return load_scene(path)


@pytest.fixture(scope="module")
def whole(scene, tmp_path_factory):
    """An uninterrupted run: (summary, out folder)."""
    out = tmp_path_factory.mktemp("whole3d")
    fresh_taichi()
    return run_scene(scene, out, emit=quiet, render=False), out


def test_3d_run_writes_3d_results(scene, whole):
    summary, out = whole
    N = summary["particles"]
    K = scene.sim.n_controls
    assert summary["dim"] == 3 and 100 <= N <= 400 and json.loads((out / "summary.json").read_text()) == summary
    meta, arrays = load_result(out)  # every array checked against the 3D settings stored with it
    assert arrays["controls"].shape == (2, K, N, 3, 3) and arrays["final_x"].shape == (N, 3)
    assert arrays["init_x"].shape == (2, N, 3) and arrays["init_F"].shape == (2, N, 3, 3)
    assert arrays["target_grid"].shape == (12, 12, 12) and arrays["target_points"].shape[1] == 3
    assert summary["loss_final"] < summary["loss_initial"]
    # round 2 starts where round 1 ends (carry_state), not at the sampled ball
    assert not np.array_equal(arrays["init_x"][1], arrays["init_x"][0])
    rest = problem.rest_node_mass(scene.sim, 12)
    mass = splat_grid(arrays["final_x"], scene.sim.m_p, 12)
    assert summary["iou"] == problem.iou(problem.occupied(mass, rest), problem.occupied(arrays["target_grid"], rest))
    assert 0.0 < summary["iou"] < 1.0 and summary["mass_error"] == problem.mass_error(mass, arrays["target_grid"])


def test_3d_resume_is_bit_identical(scene, whole, tmp_path):
    _, ref = whole
    fresh_taichi()
    first = run_scene(scene, tmp_path, emit=quiet, render=False, should_stop=StopAt(3))
    assert first["interrupted"] and (tmp_path / "checkpoint.npz").is_file()
    meta, arrays = load_npz(tmp_path / "checkpoint.npz", "checkpoint")
    assert arrays["opt_S"].shape[1] == scene.sim.n_controls * arrays["start_x"].shape[1] * 9  # K N dim^2
    fresh_taichi()
    run_scene(scene, tmp_path, resume=True, emit=quiet, render=False)
    _, a = load_npz(ref / "result.npz", "result")
    _, b = load_npz(tmp_path / "result.npz", "result")
    assert set(a) == set(b)
    for key in a:
        assert np.array_equal(a[key], b[key]), key


def test_check_passes_on_a_3d_scene(scene):
    fresh_taichi()
    lines = []
    args = argparse.Namespace(steps=12, particles=10_000, tol_tape=1e-6, tol_fd=1e-5)  # the run's own shapes
    assert check_scene(scene, args, emit=lines.append), lines
    assert lines[0].startswith(f"{scene.name} (reduced: ") and "12 steps, stride 4, f64, 3D)" in lines[0]
    assert lines[1].startswith("  manual vs ti.ad.Tape:              relative error ") and lines[-1] == "  OK"
    assert float(lines[1].split("relative error ")[1].split()[0]) <= 1e-6
    rel = float(lines[2].split("relative error ")[1].split()[0])
    assert rel <= 1e-5  # the worst of the 3 directions
