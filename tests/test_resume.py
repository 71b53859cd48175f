"""What `run` reads back and what it leaves in its output folder (mls_mpm/run.py, checkpoint.py, result.py, lock.py):
a damaged or crafted checkpoint.npz or result.npz is refused with one line naming the file, the entry and what was
expected; a resume with other settings names them; a failed --resume creates nothing; a full disk is one line and
leaves no partial file; a second job in a held folder is refused; files are 0666 minus the umask; a finished run
removes an earlier run's renders and a killed run's temp files; an interrupted rendering keeps the result.

Scene: tests/data/tiny.toml. Checkpoints are made by run._save_checkpoint from synthetic states (no simulation);
the few real runs share one Taichi runtime per run as tests/test_run.py does.
"""
import errno
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import taichi as ti

import mls_mpm.render_run
from mls_mpm import SimConfig, problem, runtime
from mls_mpm import run as run_module
from mls_mpm.checkpoint import CheckpointError, load_npz, save_npz
from mls_mpm.cli import main
from mls_mpm.errors import Interrupted
from mls_mpm.lock import FolderBusyError, folder_lock
from mls_mpm.result import load_result
from mls_mpm.run import run_scene
from mls_mpm.scene import load_scene

TINY = Path(__file__).resolve().parent / "data" / "tiny.toml"
BASE = ["optimize.iterations=1", "optimize.tol=0.0", "sim.schedule=serial"]
ROOT = Path(__file__).resolve().parents[1]


def scene_of(*overrides):
    return load_scene(TINY, [*BASE, *overrides])


def fresh_taichi():
    """A fresh Taichi runtime before each run_scene (its reverse kernels then load from the offline cache)."""
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


def one_line(e):
    text = str(e.value)
    assert "\n" not in text and "Traceback" not in text
    return text


# ---------------------------------------------------------------------------------------------------------
# Checkpoints: synthetic ones, written the way a run writes them

def write_checkpoint(scene, out, method_state=None, rounds=0, schedule="serial"):
    """A checkpoint of `scene` in the middle of round rounds + 1, as run_scene saves it (made in `schedule`)."""
    prob = problem.build(scene)
    N, K = len(prob.x0), scene.sim.n_controls
    rng = np.random.default_rng(0)
    done = [run_module.OptimizeResult(0.01 * rng.standard_normal((K, N, 2, 2)), [2e-2, 1e-2], 1, False,
                                      "iteration budget", [0.1]) for _ in range(rounds)]
    start = run_module._initial_state(prob)
    state = method_state or {"iteration": 1, "k": 2, "losses": [2e-2, 1.5e-2], "grad_norms": [0.1] * 6,
                             "g_first": 0.1, "improved": True, "small": False, "steps": [0.1] * K,
                             "stop_reason": "", "converged": False,
                             "controls": 0.01 * rng.standard_normal((K, N, 2, 2)), "loss": 1.4e-2}
    run_module._save_checkpoint(out / "checkpoint.npz", scene, schedule, done, [start] * (rounds + 1), state, 3.0)
    return prob


def load_checkpoint(scene, out):
    return run_module._load_checkpoint(out / "checkpoint.npz", scene, problem.build(scene))


def test_a_written_checkpoint_loads_back_exactly(tmp_path):
    scene = scene_of("optimize.rounds=2")
    write_checkpoint(scene, tmp_path, rounds=1)
    done, starts, state, elapsed = load_checkpoint(scene, tmp_path)
    assert len(done) == 1 and len(starts) == 2 and elapsed == 3.0
    assert state["k"] == 2 and state["losses"] == [2e-2, 1.5e-2] and state["controls"].shape[0] == 4
    meta, arrays = load_npz(tmp_path / "checkpoint.npz", "checkpoint")
    assert arrays and load_npz(tmp_path / "checkpoint.npz", "checkpoint", meta_only=True) == (meta, {})


def edit_checkpoint(path, arrays=None, meta=None, drop=()):
    meta0, arrays0 = load_npz(path, "checkpoint")
    arrays0.update(arrays or {})
    for key in drop:
        (arrays0 if key in arrays0 else meta0["opt"]).pop(key)
    for key, value in (meta or {}).items():
        target = meta0
        *parents, last = key.split(".")
        for p in parents:
            target = target[p]
        target[last] = value
    save_npz(path, meta0, arrays0)


@pytest.mark.parametrize("change,needle", [
    (dict(drop=["start_x"]), "lacks the array start_x (a float array of shape (1, {N}, 2))"),
    (dict(drop=["opt_controls"]), "lacks the array opt_controls (a float array of shape (4, {N}, 2, 2))"),
    (dict(arrays={"start_F": np.zeros((1, 7, 2, 2))}), "array start_F is float64 of shape (1, 7, 2, 2): expected a "
                                                      "float array of shape (1, {N}, 2, 2)"),
    (dict(arrays={"opt_controls": np.zeros((4, 5), np.int64)}), "array opt_controls is int64 of shape (4, 5)"),
    (dict(arrays={"opt_controls": np.full((4, 1, 2, 2), np.nan)}), "array opt_controls is float64 of shape (4, 1"),
    (dict(drop=["k"]), "opt.k is nothing: expected an integer >= 0"),
    (dict(meta={"opt.steps": [0.1, 0.1]}), "opt.steps is [0.1, 0.1]: expected a list of 4 numbers"),
    (dict(meta={"opt.losses": []}), "opt.losses is empty"),
    (dict(meta={"rounds": {"a": 1}}), "rounds is {\"a\": 1}: expected a list of at most 1 finished round(s)"),
    (dict(meta={"elapsed": "soon"}), "elapsed is \"soon\": expected a number"),
])
def test_a_crafted_checkpoint_is_refused_with_one_line(tmp_path, change, needle):
    """The right fingerprint with a missing or wrong entry: CheckpointError naming the file, the entry and what
    was expected (a KeyError or ValueError deep in the optimizer before)."""
    scene = scene_of()
    N = len(write_checkpoint(scene, tmp_path).x0)
    if "nan" in repr(change):
        change = dict(arrays={"opt_controls": np.full((4, N, 2, 2), np.nan)})
        needle = "array opt_controls holds NaN or Inf"
    edit_checkpoint(tmp_path / "checkpoint.npz", **change)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(scene, tmp_path)
    text = one_line(e)
    assert text.startswith(f"{tmp_path / 'checkpoint.npz'}: ") and needle.replace("{N}", str(N)) in text, text


def test_a_crafted_lbfgs_checkpoint_with_unequal_pairs_is_refused(tmp_path):
    scene = scene_of("optimize.method=lbfgs")
    prob = problem.build(scene)
    n = scene.sim.n_controls * len(prob.x0) * 4
    K_shape = (scene.sim.n_controls, len(prob.x0), 2, 2)
    state = {"iteration": 2, "losses": [3.0, 2.0, 1.0], "grad_norms": [1.0, 1.0], "stop_reason": "",
             "converged": False, "g": np.ones(K_shape), "S": np.ones((2, n)), "Y": np.ones((1, n)),
             "controls": np.zeros(K_shape), "loss": 1.0}
    write_checkpoint(scene, tmp_path, state)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(scene, tmp_path)
    assert "opt_S and opt_Y hold 2 and 1 pairs" in one_line(e)
    edit_checkpoint(tmp_path / "checkpoint.npz", arrays={"opt_Y": np.ones((2, n - 1))})
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(scene, tmp_path)
    assert f"array opt_Y is float64 of shape (2, {n - 1}): expected a float array of shape (any, {n})" in one_line(e)


def test_a_resume_under_auto_steps_in_the_checkpoints_schedule(tmp_path):
    """sim.schedule = "auto" resolves in each process (mls_mpm/affinity.py's probe can come out otherwise), so a
    resume steps in the schedule its checkpoint names (run._resumed_config), either one; a checkpoint that names none
    (written before checkpoints did) resumes under auto; a scene that names its schedule keeps it; a crafted value is
    refused with one line."""
    auto = scene_of("sim.schedule=auto")
    path = tmp_path / "checkpoint.npz"
    for schedule in ("serial", "parallel"):
        write_checkpoint(auto, tmp_path, schedule=schedule)
        cfg = run_module._resumed_config(path, auto.sim)
        assert cfg.schedule == schedule and cfg.replace(schedule="auto") == auto.sim  # nothing else changes
    meta, arrays = load_npz(path, "checkpoint")
    del meta["schedule"]
    save_npz(path, meta, arrays)
    assert run_module._resumed_config(path, auto.sim) is auto.sim
    serial = scene_of()
    write_checkpoint(serial, tmp_path, schedule="parallel")  # not made by this scene: its fingerprint refuses it later
    assert run_module._resumed_config(path, serial.sim) is serial.sim
    write_checkpoint(auto, tmp_path)
    edit_checkpoint(path, meta={"schedule": "sideways"})
    with pytest.raises(CheckpointError) as e:
        run_module._resumed_config(path, auto.sim)
    assert one_line(e) == (f'{path}: schedule is "sideways": expected "serial" or "parallel"; not a checkpoint of '
                           "this program; delete it or re-run")


def test_a_resume_with_other_settings_names_them(tmp_path):
    write_checkpoint(scene_of(), tmp_path)
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(scene_of("optimize.lr=0.05"), tmp_path)
    assert one_line(e).endswith("checkpoint.npz: made with other scene settings (optimize.lr: 0.1 in the checkpoint, "
                                "0.05 now); drop --resume to start over, or use the settings it was made with")
    with pytest.raises(CheckpointError) as e:
        load_checkpoint(scene_of("sim.steps=25", "sim.E=80.0", "sim.nu=0.2", "loss.kind=log_mass",
                                 "optimize.method=adam"), tmp_path)
    assert ("(loss.kind: \"mass\" in the checkpoint, \"log_mass\" now; optimize.method: \"gd\" in the checkpoint, "
            "\"adam\" now; sim.E: 88.0 in the checkpoint, 80.0 now; and 2 more)") in one_line(e)


def test_a_failed_resume_creates_nothing(tmp_path):
    out = tmp_path / "new" / "run"
    with pytest.raises(CheckpointError) as e:
        run_scene(scene_of(), out, resume=True, emit=lambda *_: None)
    assert f"{out / 'checkpoint.npz'}: no such file" in one_line(e)
    assert not (tmp_path / "new").exists()


# ---------------------------------------------------------------------------------------------------------
# One finished run, into a folder holding an earlier run's renders and a killed run's temp files, with a
# rendering that a signal interrupts, under umask 027

STALE = ["frames/frame_00000.png", "frames/frame_00001.png", "animation.gif", "sheet.png", "loss.png",
         "animation.mp4"]
TEMPS = [".result.npz.k2j4_x.tmp", ".sheet.png.4242.tmp", "frames/.frame_00003.png.4242.tmp"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("finished")
    for name in STALE + TEMPS + ["notes.txt"]:
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(b"old")
    seen = {}

    def render_run(out_dir, emit=print, should_stop=None, **kwargs):
        seen["folder"] = sorted(p.name for p in Path(out_dir).iterdir())
        seen["should_stop"] = should_stop
        raise Interrupted("stop")

    lines = []
    stop = lambda: False  # noqa: E731  (passed through to render_run)
    previous = os.umask(0o027)
    try:
        with pytest.MonkeyPatch.context() as m:
            m.setattr(mls_mpm.render_run, "render_run", render_run)
            fresh_taichi()
            summary = run_scene(scene_of(), out, emit=lines.append, should_stop=stop, render=True)
    finally:
        os.umask(previous)
    return summary, out, lines, seen, stop


def test_a_finished_run_removes_the_renders_of_an_earlier_one(finished):
    summary, out, lines, seen, _ = finished
    assert all(not (out / name).exists() for name in STALE) and not (out / "frames").exists()
    assert (out / "notes.txt").read_bytes() == b"old"  # not an output of mls-mpm: kept
    assert f"removed the renders of an earlier run from {out}: frames/, animation.gif, sheet.png, loss.png, " \
           "animation.mp4" in lines
    # removed before rendering: render_run found only this run's files
    assert seen["folder"] == [".lock", "notes.txt", "result.npz", "summary.json"]


def test_a_run_removes_temp_files_a_killed_run_left(finished):
    _, out, lines, _, _ = finished
    assert not any((out / name).exists() for name in TEMPS)
    assert f"removed 3 temp file(s) left in {out} by a killed run" in lines


def test_result_files_honour_the_umask(finished):
    """0666 minus the umask (027 here: 0640), not mkstemp's 0600."""
    _, out, _, _, _ = finished
    for name in ("result.npz", "summary.json"):
        assert (out / name).stat().st_mode & 0o777 == 0o640, name


def test_an_interrupted_rendering_keeps_the_result(finished):
    summary, out, lines, seen, stop = finished
    assert seen["should_stop"] is stop
    assert summary["interrupted"] is True and summary["render_interrupted"] is True
    assert summary["loss_final"] < summary["loss_initial"] and "iou" in summary
    assert (out / "result.npz").is_file() and not (out / "checkpoint.npz").exists()
    assert not (out / ".lock").exists()
    assert lines[-1] == f"rendering interrupted: the result is saved in {out}; `mls-mpm render {out}` renders it"
    load_result(out)


# ---------------------------------------------------------------------------------------------------------
# result.npz read back (render uses load_result)

def crafted_result(finished, tmp_path, arrays=None, drop=(), settings=None):
    _, out, _, _, _ = finished
    meta, a = load_npz(out / "result.npz", "result")
    a.update(arrays or {})
    for key in drop:
        a.pop(key)
    if settings:
        section, key, value = settings
        if value is None:
            meta["settings"][section].pop(key)
        else:
            meta["settings"][section][key] = value
    save_npz(tmp_path / "result.npz", meta, a)
    return a


@pytest.mark.parametrize("case", ["controls_K", "init_F_N", "colors", "final_x_int", "round_lengths",
                                  "target_points", "render_size", "sim_steps", "target_grid"])
def test_a_crafted_result_is_refused_with_one_line(finished, tmp_path, case):
    _, out, _, _, _ = finished
    _, a = load_npz(out / "result.npz", "result")
    R, K, N = a["controls"].shape[:3]
    arrays, drop, settings = {}, (), None
    if case == "controls_K":
        arrays = {"controls": np.zeros((R, K + 1, N, 2, 2))}
        needle = f"array controls is float64 of shape ({R}, {K + 1}, {N}, 2, 2): expected a float array of shape " \
                 f"(any, {K}, any, 2, 2)"
    elif case == "init_F_N":
        arrays = {"init_F": np.zeros((R, N - 1, 2, 2))}
        needle = f"expected a float array of shape ({R}, {N}, 2, 2)"
    elif case == "colors":
        drop = ("colors",)
        needle = "lacks colors"
    elif case == "final_x_int":
        arrays = {"final_x": np.zeros((N, 2), np.int32)}
        needle = f"array final_x is int32 of shape ({N}, 2): expected a float array"
    elif case == "round_lengths":
        arrays = {"round_lengths": np.array([7])}
        needle = "round_lengths [7] do not add up to the 2 losses of 1 round(s)"
    elif case == "target_points":
        arrays = {"target_points": np.zeros((5, 2))}
        needle = "lacks the array target_colors (a float array of shape (5, 3))"
        drop = ("target_colors",)
    elif case == "render_size":
        settings = ("render", "size", None)
        needle = "settings.render.size is nothing: expected an integer >= 0"
    elif case == "sim_steps":
        settings = ("sim", "steps", -3)
        needle = "settings.sim are not a valid simulation (steps = -3: expected an integer >= 1)"
    else:
        arrays = {"target_grid": np.zeros((32, 16))}
        needle = "array target_grid is float64 of shape (32, 16): expected a float array of shape (32, 32)"
    crafted_result(finished, tmp_path, arrays, drop, settings)
    with pytest.raises(CheckpointError) as e:
        load_result(tmp_path)
    text = one_line(e)
    assert text.startswith(f"{tmp_path / 'result.npz'}: ") and needle in text, text


# ---------------------------------------------------------------------------------------------------------
# A full disk, and two jobs in one folder

def call(*argv):
    """main(argv) -> (code, stderr), restoring the signal handlers `run` installs."""
    import contextlib
    import io
    import signal

    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    err = io.StringIO()
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    return code, err.getvalue()


@pytest.mark.parametrize("victim", ["checkpoint.npz", "result.npz"])
def test_a_full_disk_is_one_line_and_leaves_no_partial_file(tmp_path, monkeypatch, victim):
    real = np.savez
    key = {"checkpoint.npz": "start_x", "result.npz": "final_x"}[victim]

    def savez(fh, **arrays):
        if key in arrays:
            fh.write(b"PK\x03\x04 half a file")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fh, **arrays)

    monkeypatch.setattr(np, "savez", savez)
    fresh_taichi()
    code, stderr = call("run", TINY, "--out", tmp_path, "--no-render", "--quiet", *sum((["--set", o] for o in BASE), []))
    assert code == 2 and stderr.splitlines() == [
        f"mls-mpm: error: {tmp_path / victim}: cannot write it (No space left on device); free some space or pick "
        "another --out"], stderr
    left = sorted(p.name for p in tmp_path.iterdir())
    # no partial file, no temp file, no lock; a failed result keeps the checkpoint a --resume finishes from
    assert left == ([] if victim == "checkpoint.npz" else ["checkpoint.npz"]), left


HOLDER = textwrap.dedent("""
    import sys, time
    from mls_mpm.lock import folder_lock
    with folder_lock(sys.argv[1], "render"):
        print("locked", flush=True)
        time.sleep(120)
""")


def test_a_second_job_in_a_held_folder_is_refused(tmp_path):
    """A real second process holds the folder: run is refused with one line naming the folder and the PID, and
    writes nothing; once the holder is gone (killed: the kernel drops its lock) a run may use the folder."""
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                              cwd=ROOT)
    try:
        lines = []
        for line in holder.stdout:  # after Taichi's banner, which importing mls_mpm prints
            lines.append(line.strip())
            if lines[-1] == "locked":
                break
        assert lines[-1:] == ["locked"], lines
        fresh_taichi()
        with pytest.raises(FolderBusyError) as e:
            run_scene(scene_of(), tmp_path, emit=lambda *_: None, render=False)
        assert one_line(e) == (f"{tmp_path}: another mls-mpm job is using this output folder (PID {holder.pid}, "
                               "mls-mpm render); wait for it to end or pick another folder for this run")
        assert sorted(p.name for p in tmp_path.iterdir()) == [".lock"]
    finally:
        holder.kill()
        holder.wait()
    with folder_lock(tmp_path, "run") as path:  # the SIGKILLed holder's lock is gone with it
        assert path.read_text() == f"{os.getpid()} run\n"
    assert not (tmp_path / ".lock").exists()
    with folder_lock(tmp_path, "run"):
        with pytest.raises(FolderBusyError):  # a second lock in the same process is refused too
            with folder_lock(tmp_path, "render"):
                pass


def test_checkpoints_are_throttled_and_the_last_one_before_an_interrupt_is_written():
    """run._Throttled: the first checkpoint is written at once, later ones within CHECKPOINT_SECONDS of the last
    write are held back (only the newest is kept), one past it is written, and flush() writes the one held back
    (what run does when the optimizer returns interrupted), once."""
    now = [100.0]
    written = []
    saver = run_module._Throttled(lambda state, at: written.append((state["i"], at)), clock=lambda: now[0])
    step = run_module.CHECKPOINT_SECONDS / 4
    for i in range(10):
        saver({"i": i})
        now[0] += step
    # writes at t = 100 (i = 0), 100 + 4 steps (i = 4), 100 + 8 steps (i = 8); i = 9 is held back
    assert written == [(0, 100.0), (4, 100.0 + 4 * step), (8, 100.0 + 8 * step)]
    saver.flush()
    assert written[-1] == (9, 100.0 + 9 * step)  # with the clock reading of its own call
    saver.flush()
    assert len(written) == 4  # nothing held back any more


def test_a_checkpoint_that_is_slow_to_write_is_written_less_often():
    """run._Throttled: after a write that took t seconds the next waits t / CHECKPOINT_SHARE when that is longer than
    CHECKPOINT_SECONDS, so writing takes at most that share of the run; a quick write brings the wait back down."""
    now = [0.0]
    written = []
    took = {0: 0.5, 1: 0.0}  # seconds each write takes, by the order of writes

    def write(state, at):
        now[0] += took.get(len(written), 0.0)
        written.append((state["i"], at))

    saver = run_module._Throttled(write, clock=lambda: now[0])
    slow = 0.5 / run_module.CHECKPOINT_SHARE
    assert slow > run_module.CHECKPOINT_SECONDS
    step = 0.25
    for i in range(200):
        saver({"i": i})
        now[0] += step
        if len(written) == 3:
            break
    (i0, t0), (i1, t1), (i2, t2) = written
    assert t0 == 0.0 and t1 - t0 >= slow and t1 - t0 < slow + step + 0.5  # waited for the slow write
    assert t2 - t1 >= run_module.CHECKPOINT_SECONDS and t2 - t1 < run_module.CHECKPOINT_SECONDS + step
