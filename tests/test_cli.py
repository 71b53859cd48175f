"""The command line (mls_mpm/cli.py): argument parsing, `run` end to end with its files, `render` reproducing a
run's frames, `check`, one-line refusals of bad input (exit 2, nothing written), and a real SIGINT that leaves a
checkpoint from which `--resume` finishes exactly like an uninterrupted run.

Scene: tests/data/tiny.toml (32 x 32 grid, ~300 particles, 20 steps, stride 5, K = 4 controls, frames of 64
pixels every 5 steps).
"""
import contextlib
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import taichi as ti
from PIL import Image

from mls_mpm import SimConfig, runtime
from mls_mpm.checkpoint import load_npz
from mls_mpm.cli import build_parser, main
from mls_mpm.frames import frame_paths
from mls_mpm.run import run_scene
from mls_mpm.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.toml"
FRAMES = [f"frame_{i:05d}.png" for i in range(5)]  # steps 0, 5, 10, 15, 20


def fresh_taichi():
    """Restart Taichi (CPU, float64, as conftest.py sets it) before a command that simulates.

    Taichi's offline cache only serves the fields of a fresh runtime: each further Simulator in one process
    recompiles its reverse kernels (~10 s of CPU), a fresh runtime loads them from the cache (~2 s). Each command
    here runs as if in its own `mls-mpm` process; nothing Taichi-backed outlives a test of this module.
    """
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


def call(*argv):
    """main(argv) -> (exit code, stdout, stderr), restoring the SIGINT/SIGTERM handlers `run` installs."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    return code, out.getvalue(), err.getvalue()


def files_in(folder):
    folder = Path(folder)
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")) if folder.exists() else []


# ---------------------------------------------------------------------------------------------------------
# Argument parsing alone: no scene is read and nothing is simulated.

def test_parse_run():
    a = build_parser().parse_args(["run", "s.toml", "--out", "d", "--set", "sim.steps=5", "--set", "control.stride=5",
                                   "--arch", "gpu", "--resume", "--no-render", "--quiet"])
    assert (a.command, a.scene, a.out, a.set, a.arch) == ("run", "s.toml", "d", ["sim.steps=5", "control.stride=5"],
                                                          "gpu")
    assert a.resume and a.no_render and a.quiet


def test_parse_run_defaults():
    a = build_parser().parse_args(["run", "s.toml"])
    assert (a.out, a.set, a.arch, a.resume, a.no_render, a.quiet) == (None, [], None, False, False, False)


def test_parse_check_render_bench():
    p = build_parser()
    c = p.parse_args(["check", "s.toml", "--set", "sim.steps=30"])
    assert (c.command, c.scene, c.set, c.steps, c.particles, c.tol_tape, c.tol_fd) == \
           ("check", "s.toml", ["sim.steps=30"], 12, 300, 1e-6, 1e-5)
    c = p.parse_args(["check", "s.toml", "--steps", "6", "--particles", "50", "--tol-tape", "1e-3", "--tol-fd", "0.1"])
    assert (c.steps, c.particles, c.tol_tape, c.tol_fd) == (6, 50, 1e-3, 0.1)
    r = p.parse_args(["render", "out/x", "--mode", "particles", "--size", "128", "--every", "2", "--arch", "cpu"])
    assert (r.command, r.dir, r.mode, r.size, r.every, r.arch) == ("render", "out/x", "particles", 128, 2, "cpu")
    r = p.parse_args(["render", "out/x"])
    assert (r.mode, r.size, r.every, r.arch) == (None, None, None, None)
    b = p.parse_args(["bench", "gradient", "--quick"])
    assert (b.command, b.what, b.quick) == ("bench", "gradient", True)


@pytest.mark.parametrize("argv, says", [
    ([], "the following arguments are required: command"),
    (["walk", "s.toml"], "argument command: invalid choice: 'walk'"),
    (["run"], "run: the following arguments are required: scene"),
    (["run", "s.toml", "--arch", "tpu"], "run: argument --arch: invalid choice: 'tpu'"),
    (["run", "s.toml", "--sett", "sim.steps=5"], "unrecognized arguments: --sett"),
    (["render", "d", "--mode", "wireframe"], "render: argument --mode: invalid choice: 'wireframe' (choose from "
                                             "'mass', 'color', 'particles', 'surface', 'volume')"),
    (["render", "d", "--size", "big"], "render: argument --size: expected an integer from 16 to 8192 pixels, "
                                       "got 'big'"),
    (["render", "d", "--size", "0"], "render: argument --size: expected an integer from 16 to 8192 pixels, got '0'"),
    (["render", "d", "--size", "-5"], "render: argument --size: expected an integer from 16 to 8192"),
    (["render", "d", "--size", "8"], "render: argument --size: expected an integer from 16 to 8192"),
    (["render", "d", "--size", "100000"], "render: argument --size: expected an integer from 16 to 8192"),
    (["render", "d", "--every", "0"], "render: argument --every: expected an integer >= 1, got '0'"),
    (["render", "d", "--every", "-1"], "render: argument --every: expected an integer >= 1, got '-1'"),
    (["check", "s.toml", "--steps", "1.5"], "check: argument --steps: expected an integer >= 2, got '1.5'"),
    (["check", "s.toml", "--steps", "1"], "check: argument --steps: expected an integer >= 2, got '1'"),
    (["check", "s.toml", "--particles", "0"], "check: argument --particles: expected an integer >= 1, got '0'"),
    (["check", "s.toml", "--tol-tape", "nan"], "check: argument --tol-tape: expected a finite number > 0, got 'nan'"),
    (["check", "s.toml", "--tol-tape", "0"], "check: argument --tol-tape: expected a finite number > 0, got '0'"),
    (["check", "s.toml", "--tol-fd", "-1"], "check: argument --tol-fd: expected a finite number > 0, got '-1'"),
    (["check", "s.toml", "--tol-fd", "inf"], "check: argument --tol-fd: expected a finite number > 0, got 'inf'"),
    (["bench", "everything"], "bench: argument what: invalid choice: 'everything'"),
])
def test_parser_refuses_with_one_line(argv, says, capsys):
    """Every bad command line: exit 2 and one line naming the option and what it expects (no usage block)."""
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [err.rstrip("\n")], err
    assert err.startswith(f"mls-mpm: error: {says}"), err
    assert err.rstrip().endswith("--help")
    assert main(argv) == 2  # main returns the code; nothing is simulated (s.toml and d do not exist)
    assert capsys.readouterr().err == err


def test_parser_accepts_the_limits():
    from mls_mpm.scene import RENDER_MODES, RENDER_SIZE_MAX, RENDER_SIZE_MIN

    p = build_parser()
    for size in (RENDER_SIZE_MIN, RENDER_SIZE_MAX):
        assert p.parse_args(["render", "d", "--size", str(size), "--every", "1"]).size == size
    assert [p.parse_args(["render", "d", "--mode", m]).mode for m in RENDER_MODES] == list(RENDER_MODES)
    c = p.parse_args(["check", "s.toml", "--steps", "2", "--particles", "1", "--tol-tape", "1e-300", "--tol-fd", "5"])
    assert (c.steps, c.particles, c.tol_tape, c.tol_fd) == (2, 1, 1e-300, 5.0)


def test_help_shows_defaults(capsys):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["check", "--help"])
    assert e.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 12)" in text and "(default: 300)" in text and "(default: 1e-06)" in text


def test_morph_help_states_the_presets(capsys):
    """The budgets and grids `mls-mpm morph --help` gives are those of morph.QUALITIES and QUALITIES_3D (it said
    110 s for the default's 105 before, and nothing of 3D)."""
    from mls_mpm.morph import QUALITIES, QUALITIES_3D

    with pytest.raises(SystemExit):
        build_parser().parse_args(["morph", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    budgets = re.search(r"\(default: (\d+) fast, (\d+) default, none best; 3D: (\d+) fast and default\)", text)
    assert budgets, text
    assert [float(b) for b in budgets.groups()] == [QUALITIES["fast"].max_seconds, QUALITIES["default"].max_seconds,
                                                    QUALITIES_3D["fast"].max_seconds]
    assert QUALITIES_3D["default"].max_seconds == QUALITIES_3D["fast"].max_seconds
    assert QUALITIES["best"].max_seconds == QUALITIES_3D["best"].max_seconds == 0
    grids = re.search(r"fast: a (\d+)\^2 preview within ~30 s \(3D: (\d+)\^3\); default: (\d+)\^2 \(3D: (\d+)\^3\)",
                      text)
    assert grids, text
    assert [int(g) for g in grids.groups()] == [QUALITIES["fast"].n_grid, QUALITIES_3D["fast"].n_grid,
                                                QUALITIES["default"].n_grid, QUALITIES_3D["default"].n_grid]
    assert f"2D: two rounds of {QUALITIES['best'].iterations} iterations" in text and QUALITIES["best"].rounds == 2


# ---------------------------------------------------------------------------------------------------------
# `mls-mpm run` end to end, then `mls-mpm render` of its result

@pytest.fixture(scope="module")
def e2e(tmp_path_factory):
    out = tmp_path_factory.mktemp("e2e") / "run"
    fresh_taichi()
    before = signal.getsignal(signal.SIGINT)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    stdout, stderr = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(["run", str(TINY), "--out", str(out), "--set", "optimize.iterations=2"])
        after = signal.getsignal(signal.SIGINT)
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    return dict(out=out, code=code, stdout=stdout.getvalue(), stderr=stderr.getvalue(), before=before, after=after)


def test_run_writes_every_file(e2e):
    out = e2e["out"]
    assert e2e["code"] == 0, e2e["stderr"]
    assert [p.name for p in frame_paths(out / "frames")] == FRAMES
    assert sorted(p.name for p in (out / "frames").iterdir()) == FRAMES  # no temporary or stray files
    assert {"result.npz", "summary.json", "animation.gif", "sheet.png", "loss.png"} <= set(os.listdir(out))
    assert not (out / "checkpoint.npz").exists()
    for name in FRAMES:
        with Image.open(out / "frames" / name) as im:
            assert im.size == (64, 64)
    with Image.open(out / "animation.gif") as gif:
        assert gif.n_frames == len(FRAMES)
    with Image.open(out / "loss.png") as im:
        assert im.format == "PNG" and im.size == (640, 400)


def test_sheet_shows_initial_middle_final(e2e):
    """sheet.png: four 64-pixel panels 8 pixels apart under a 20-pixel label row: frames 0, 2 and 4, then the target."""
    frames = e2e["out"] / "frames"
    sheet = np.asarray(Image.open(e2e["out"] / "sheet.png").convert("RGB"))
    assert sheet.shape == (20 + 64, 4 * 64 + 3 * 8, 3)
    for panel, name in enumerate([FRAMES[0], FRAMES[2], FRAMES[4]]):
        frame = np.asarray(Image.open(frames / name).convert("RGB"))
        assert np.array_equal(sheet[20:, panel * 72:panel * 72 + 64], frame), name
    first = np.asarray(Image.open(frames / FRAMES[0]).convert("RGB"))
    last = np.asarray(Image.open(frames / FRAMES[4]).convert("RGB"))
    assert not np.array_equal(first, last)  # the body moved


def test_run_reports_progress_and_summary(e2e):
    summary = json.loads((e2e["out"] / "summary.json").read_text())
    lines = e2e["stdout"].splitlines()
    assert lines[0].startswith("tiny: ") and "optimizer gd" in lines[0]
    assert sum(line.startswith("temporal iteration ") for line in lines) == 2
    assert f"loss {summary['loss_initial']:.6e} -> {summary['loss_final']:.6e}, iou {summary['iou']:.3f}" in lines[-1]
    assert summary["iterations"] == 2 and summary["loss_final"] < summary["loss_initial"]
    assert e2e["stderr"] == ""


def test_run_restores_signal_handlers(e2e):
    assert e2e["after"] is e2e["before"]


def test_render_reproduces_the_runs_frames(e2e, tmp_path):
    """`mls-mpm render DIR` re-simulates result.npz and writes the same bytes as the run did."""
    shutil.copy(e2e["out"] / "result.npz", tmp_path / "result.npz")
    fresh_taichi()
    code, stdout, stderr = call("render", tmp_path)
    assert code == 0, stderr
    assert [p.name for p in frame_paths(tmp_path / "frames")] == FRAMES
    for name in FRAMES:
        assert (tmp_path / "frames" / name).read_bytes() == (e2e["out"] / "frames" / name).read_bytes(), name
    for name in ("animation.gif", "sheet.png", "loss.png"):
        assert (tmp_path / name).read_bytes() == (e2e["out"] / name).read_bytes(), name


def test_render_in_a_fresh_process(e2e, tmp_path):
    """`mls-mpm render` as users run it: a new process, where nothing has started Taichi before the renderer."""
    shutil.copy(e2e["out"] / "result.npz", tmp_path / "result.npz")
    res = subprocess.run(cli("render", tmp_path, "--every", "20"), cwd=ROOT, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    assert [p.name for p in frame_paths(tmp_path / "frames")] == ["frame_00000.png", "frame_00001.png"]
    first = (tmp_path / "frames" / "frame_00000.png").read_bytes()
    assert first == (e2e["out"] / "frames" / "frame_00000.png").read_bytes()


def test_render_options(e2e, tmp_path):
    shutil.copy(e2e["out"] / "result.npz", tmp_path / "result.npz")
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "frame_00007.png").write_bytes(b"left over")  # an older, longer render
    fresh_taichi()
    code, _, stderr = call("render", tmp_path, "--size", "32", "--every", "10", "--mode", "particles")
    assert code == 0, stderr
    assert [p.name for p in frame_paths(tmp_path / "frames")] == FRAMES[:3]  # steps 0, 10, 20; leftovers removed
    for p in frame_paths(tmp_path / "frames"):
        with Image.open(p) as im:
            assert im.size == (32, 32)
    with Image.open(tmp_path / "animation.gif") as gif:
        assert gif.n_frames == 3


# ---------------------------------------------------------------------------------------------------------
# `mls-mpm check`

CHECK_LINE = re.compile(r"relative error (\S+) \(tolerance (\S+)\)")


def test_check_passes_and_prints_relative_errors():
    fresh_taichi()
    code, stdout, stderr = call("check", TINY)
    assert code == 0, stdout + stderr
    found = [(float(a), float(b)) for a, b in CHECK_LINE.findall(stdout)]
    assert [tol for _, tol in found] == [1e-6, 1e-5], stdout  # Tape, then finite differences
    assert all(0.0 <= err <= tol for err, tol in found), stdout
    assert stdout.rstrip().endswith("OK")
    assert "300 particles, 12 steps" in stdout


def test_check_passes_on_the_transport_loss():
    """The OT loss (transport on the 16 grid, eq 11 on the 32 grid): check runs Sinkhorn to round-off and steps its
    finite differences by check.EPS_OT; both comparisons pass (at the production tolerance and step 1e-6 the
    finite differences were 2e-5 off)."""
    sets = ["loss.kind=ot", "loss.grids=[16, 32]", "loss.weights=[1.0, 0.0]", "loss.mass_weights=[0.0, 1.0]"]
    fresh_taichi()
    code, stdout, stderr = call("check", TINY, "--steps", "6", "--particles", "120",
                                *[a for s in sets for a in ("--set", s)])
    assert code == 0, stdout + stderr
    found = [(float(a), float(b)) for a, b in CHECK_LINE.findall(stdout)]
    assert len(found) == 2 and all(0.0 <= err <= tol for err, tol in found), stdout


def test_check_keeps_a_colour_loss_transport_term():
    """check's reduced copy of a colour loss keeps its grids (eq 13 and colour transport) and subsamples the
    particles' colours."""
    from mls_mpm.check import reduced
    from mls_mpm.scene import load_scene

    images = ROOT / "scenes" / "images"
    scene = load_scene(TINY, [f"scene.initial={images / 'color_halves.png'}",
                              f"scene.target={images / 'color_swap_target.png'}", "loss.kind=color",
                              "loss.grids=[16, 32]", "loss.weights=[0.0, 1.0]", "loss.ot_weights=[1.0, 0.0]"])
    _, x0, loss = reduced(scene, 6, 50)
    assert [(g.kind, g.res) for g in loss.grids] == [("color", 32), ("color_ot", 16)]
    assert len(loss.colors) == len(x0) == 50
    assert all(g.tol == 1e-12 for g in loss.grids if g.kind == "color_ot")


def test_render_refuses_a_folder_another_job_holds(tmp_path):
    """`render` takes the output folder's lock like `run`: while another job holds it, one line, exit 2."""
    from mls_mpm.lock import folder_lock

    with folder_lock(tmp_path, "run"):
        code, _, stderr = call("render", tmp_path)
    assert code == 2
    assert stderr.count("\n") == 1 and "another mls-mpm job is using this output folder" in stderr
    code, _, stderr = call("render", tmp_path)  # released: now the missing result is what is wrong
    assert code == 2 and "result.npz" in stderr and "another mls-mpm job" not in stderr


def test_check_fails_beyond_tolerance(monkeypatch):
    """A manual gradient 1% off (a deliberately broken backward) fails both comparisons, far above the round-off
    floor, with exit code 1 and FAILED."""
    from mls_mpm.simulator import Simulator

    right = Simulator.backward
    monkeypatch.setattr(Simulator, "backward", lambda self, *a, **k: 1.01 * right(self, *a, **k))
    fresh_taichi()
    code, stdout, _ = call("check", TINY)
    assert code == 1
    assert "FAILED" in stdout
    errors = [float(e[0]) for e in CHECK_LINE.findall(stdout)]
    assert len(errors) == 2 and all(9e-3 < e < 1.1e-2 for e in errors), errors


# ---------------------------------------------------------------------------------------------------------
# Bad input: exit code 2, one line on stderr starting "mls-mpm: error:", no traceback, nothing written.

@pytest.fixture
def images(tmp_path):
    """blank.png: all white, no material."""
    Image.fromarray(np.full((16, 16), 255, np.uint8)).save(tmp_path / "blank.png")
    return tmp_path


def assert_refused(code, stdout, stderr, *needles, header=False):
    """Exit 2 and one error line; stdout empty, or (header=True) only run's first line naming the scene."""
    assert code == 2
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("mls-mpm: error: ")
    assert "Traceback" not in stderr
    assert stdout.splitlines() == ([stdout.splitlines()[0]] if header and stdout.startswith("tiny: ") else []), stdout
    for needle in needles:
        assert needle in lines[0], lines[0]


@pytest.mark.parametrize("case", ["missing scene", "misspelled key", "wrong type", "stride > steps", "missing image",
                                  "no material"])
def test_run_refuses_bad_scenes(case, images, capfd):
    out = images / "out"
    argv, needles = {
        "missing scene": (["run", images / "nope.toml"], ["nope.toml: no such scene file"]),
        "misspelled key": (["run", TINY, "--set", "sim.n_grd=32"],
                           ["sim.n_grd = 32 (from --set): unknown key in [sim]; did you mean 'n_grid'?"]),
        "wrong type": (["run", TINY, "--set", "sim.steps=20.0"],
                       ["sim.steps = 20.0 (from --set): expected an integer >= 1"]),
        "stride > steps": (["run", TINY, "--set", "control.stride=40"],
                           ["control.stride = 40 (from --set): expected at most sim.steps = 20"]),
        "missing image": (["run", TINY, "--set", f"scene.initial={images / 'gone.png'}"],
                          ["scene.initial", "gone.png: no such image file"]),
        "no material": (["run", TINY, "--set", f"scene.target={images / 'blank.png'}"],
                        ["scene.target", "blank.png", "expected an image with material"]),
    }[case]
    code, stdout, stderr = call(*argv, "--out", out)
    captured = capfd.readouterr()  # anything written to the real file descriptors (Taichi's C++ logging)
    assert_refused(code, stdout + captured.out, stderr + captured.err, *needles)
    assert files_in(out) == [], "a refused run wrote files"


def test_run_refuses_an_output_folder_under_a_file(tmp_path):
    (tmp_path / "file").write_text("not a folder")
    code, stdout, stderr = call("run", TINY, "--out", tmp_path / "file" / "out")
    assert_refused(code, stdout, stderr, "output folder is not writable")
    assert (tmp_path / "file").read_text() == "not a folder"


def test_run_refuses_a_read_only_output_folder(tmp_path):
    """A folder nobody may write into, root included: /proc refuses new files and folders to every user. (A 0o500
    folder of our own, refused to other users, is also tried where this user is not root.)"""
    for out in (Path("/proc/self"), Path("/proc/mls-mpm-out")):
        code, stdout, stderr = call("run", TINY, "--out", out)
        assert_refused(code, stdout, stderr, "output folder is not writable", str(out))
    assert not Path("/proc/mls-mpm-out").exists()
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root may write anywhere: /proc above is its case
            code, stdout, stderr = call("run", TINY, "--out", locked / "out")
            assert_refused(code, stdout, stderr, "output folder is not writable", "--out")
            code, stdout, stderr = call("run", TINY, "--out", locked)
            assert_refused(code, stdout, stderr, "output folder is not writable")
            assert files_in(locked) == []
    finally:
        locked.chmod(0o700)


@pytest.mark.parametrize("content", ["garbage", "truncated", "empty npz", "missing"])
def test_render_refuses_a_bad_result(e2e, tmp_path, content):
    path = tmp_path / "result.npz"
    if content == "garbage":
        path.write_bytes(b"this is not a zip file")
    elif content == "truncated":
        data = (e2e["out"] / "result.npz").read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif content == "empty npz":
        np.savez(path, meta=np.array(json.dumps({"summary": {}})))
    before = files_in(tmp_path)
    code, stdout, stderr = call("render", tmp_path)
    needle = {"garbage": "not a readable result", "truncated": "not a readable result",
              "empty npz": "lacks controls", "missing": "no such file"}[content]
    assert_refused(code, stdout, stderr, "result.npz", needle)
    assert files_in(tmp_path) == before, "a refused render wrote files"


def test_resume_refuses_a_missing_or_foreign_checkpoint(tmp_path):
    fresh_taichi()
    code, stdout, stderr = call("run", TINY, "--out", tmp_path, "--resume")
    assert_refused(code, stdout, stderr, "checkpoint.npz: no such file", header=True)
    assert files_in(tmp_path) == []

    fresh_taichi()
    summary = run_scene(load_scene(TINY), tmp_path, emit=lambda *_: None, should_stop=lambda: True, render=False)
    assert summary["interrupted"]
    checkpoint = (tmp_path / "checkpoint.npz").read_bytes()
    fresh_taichi()
    code, stdout, stderr = call("run", TINY, "--out", tmp_path, "--resume", "--set", "optimize.lr=0.05")
    assert_refused(code, stdout, stderr, "checkpoint.npz: made with other scene settings", header=True)
    assert (tmp_path / "checkpoint.npz").read_bytes() == checkpoint
    assert files_in(tmp_path) == ["checkpoint.npz"]


def test_refusal_in_a_real_process(tmp_path):
    """The same through the interpreter: no Taichi banner or traceback on stderr, one line."""
    proc = subprocess.run([sys.executable, "-m", "mls_mpm.cli", "run", str(tmp_path / "nope.toml")], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [f"mls-mpm: error: {tmp_path / 'nope.toml'}: no such scene file"]


# ---------------------------------------------------------------------------------------------------------
# Signals and imports: `import mls_mpm` and `import mls_mpm.cli` load neither numpy nor Taichi, so Ctrl-C
# during start-up lands inside main, which says one line; `render` stops on SIGINT/SIGTERM like `run`.

# Sends this process SIGINT the moment `module` is first imported, then runs the CLI as its console script does.
# SIGINT gets Python's own handler first, as in a process started from a terminal: a test run started in the
# background (nohup ... &) passes SIGINT on ignored, and Python then installs no handler, so nothing is raised.
INTERRUPT_AT_IMPORT = """
import os, signal, sys

signal.signal(signal.SIGINT, signal.default_int_handler)

class Interrupt:
    def find_spec(self, name, path=None, target=None):
        if name == sys.argv[1]:
            os.kill(os.getpid(), signal.SIGINT)
        return None


sys.meta_path.insert(0, Interrupt())
from mls_mpm.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.mark.parametrize("module", ["numpy", "taichi"])
def test_ctrl_c_during_import_is_one_line(module):
    proc = subprocess.run([sys.executable, "-c", INTERRUPT_AT_IMPORT, module, "check", str(TINY)], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.splitlines() == ["mls-mpm: interrupted"]


def test_package_import_is_lazy():
    """The package's names and submodules are there on first use; importing it and the CLI loads no numpy/Taichi."""
    code = ("import sys, mls_mpm, mls_mpm.cli; heavy = {'numpy', 'taichi'} & set(sys.modules); "
            "print(sorted(heavy), mls_mpm.SimConfig.__module__, mls_mpm.Simulator.__module__, "
            "mls_mpm.MassLoss.__module__, mls_mpm.runtime.__name__, mls_mpm.SimulationError.__name__)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[-6:] == ["[]", "mls_mpm.config", "mls_mpm.simulator", "mls_mpm.losses",
                                        "mls_mpm.runtime", "SimulationError"]
    import mls_mpm

    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        mls_mpm.no_such_name


SIGNALS = [(signal.SIGINT, 130), (signal.SIGTERM, 143)]


@pytest.mark.parametrize("sig, code", SIGNALS)
def test_render_stops_on_a_signal(monkeypatch, sig, code):
    """`render` installs the same StopFlag as `run` and passes it as should_stop; Interrupted is one line, 130/143."""
    import mls_mpm.render_run
    from mls_mpm.errors import Interrupted

    seen = []

    def render_run(out_dir, mode=None, size=None, every=None, arch=None, emit=print, should_stop=None):
        seen.append(should_stop())
        signal.raise_signal(sig)  # as from the terminal: the handler only sets the flag
        seen.append(should_stop())
        raise Interrupted("rendering stopped after frame 3; the earlier frames are kept")

    monkeypatch.setattr(mls_mpm.render_run, "render_run", render_run)
    got, stdout, stderr = call("render", "some/run")
    assert (got, seen) == (code, [False, True]), stderr
    lines = [ln for ln in stderr.splitlines() if ln]
    assert lines == [f"mls-mpm: got signal {int(sig)} ({sig.name}); stopping after the current step (a second "
                     "signal stops at once)...",
                     "mls-mpm: interrupted: rendering stopped after frame 3; the earlier frames are kept"], stderr
    assert stdout == ""


@pytest.mark.parametrize("sig, code", SIGNALS)
@pytest.mark.parametrize("how", ["render_interrupted", "interrupted", "raises"])
def test_run_maps_an_interrupted_run_to_its_signal(monkeypatch, tmp_path, sig, code, how):
    """Stopped while optimizing (summary "interrupted") or while rendering (summary "render_interrupted", or
    Interrupted raised): exit 130 after SIGINT, 143 after SIGTERM, no traceback."""
    import mls_mpm.run
    from mls_mpm.errors import Interrupted

    def run_scene(scene, out, resume=False, emit=print, should_stop=None, render=True, files=None):
        signal.raise_signal(sig)
        assert should_stop()
        if how == "raises":
            raise Interrupted("rendering stopped; the result is kept, render it with mls-mpm render")
        return {"scene": scene.name, how: True}

    monkeypatch.setattr(mls_mpm.run, "run_scene", run_scene)
    got, _, stderr = call("run", TINY, "--out", tmp_path / "out")
    assert got == code, stderr
    assert "Traceback" not in stderr


# ---------------------------------------------------------------------------------------------------------
# A real SIGINT

K_BOUNDARY_BUG = ("bug: gd interrupted after the last control step of a temporal iteration checkpoints k = K; "
                  "resumed, it ends that iteration as 'gradient norm below tolerance' and stops early "
                  "(optimize.py gd: keep `small` in the checkpointed state like `improved`)")


def cli(*args):
    return [sys.executable, "-m", "mls_mpm.cli", *map(str, args)]


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_checkpoints_and_resume_finishes_the_same(tmp_path, sig, code):
    """Ctrl-C (SIGINT) or SIGTERM to a real `mls-mpm run` process: exit 130 / 143 after saving checkpoint.npz;
    `--resume` then ends with the losses, controls and final positions of an uninterrupted run, bit for bit.

    Under `sim.schedule = "auto"`, as users run: this scene (about 1,300 particles + nodes on 2 CPUs) runs in parallel
    only where mls_mpm/affinity.py's probe pinned the workers, which can fail in one process and not in another on a
    loaded machine, and the two schedules differ in round-off. The resume steps in the schedule the checkpoint names;
    the uninterrupted reference is made in that schedule, named."""
    out = tmp_path / "interrupted"
    log = tmp_path / "log.txt"
    # a budget far beyond what runs before the signal; the resume sets the real one
    with open(log, "w") as fh:
        proc = subprocess.Popen(cli("run", TINY, "--out", out, "--no-render", "--set", "optimize.iterations=100000",
                                    "--set", "optimize.tol=0.0"), cwd=ROOT, stdout=fh,
                                stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 180
        while not (out / "checkpoint.npz").exists():  # written after the first temporal iteration
            assert proc.poll() is None, f"the run ended before a checkpoint:\n{log.read_text()}"
            assert time.monotonic() < deadline, f"no checkpoint after 180 s:\n{log.read_text()}"
            time.sleep(0.02)
        proc.send_signal(sig)
        got_code = proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text()
    assert got_code == code, text
    assert f"got signal {int(sig)}" in text and "continue with --resume" in text and "Traceback" not in text
    assert "stopping after the current step" in text and "saving a checkpoint" not in text  # true while rendering too
    assert (out / "checkpoint.npz").is_file() and not (out / "result.npz").exists()
    meta, _ = load_npz(out / "checkpoint.npz", "checkpoint")
    done = meta["opt"]["iteration"]
    budget = done + 2  # at least one more whole temporal iteration after the resume
    schedule = meta["schedule"]
    assert f"({schedule} schedule)" in text

    resumed = subprocess.run(cli("run", TINY, "--out", out, "--no-render", "--resume", "--set",
                                 f"optimize.iterations={budget}", "--set", "optimize.tol=0.0"),
                             cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert "resuming from" in resumed.stdout and f"({schedule} schedule)" in resumed.stdout
    assert not (out / "checkpoint.npz").exists()

    reference = tmp_path / "whole"
    fresh_taichi()
    run_scene(load_scene(TINY, [f"optimize.iterations={budget}", "optimize.tol=0.0", f"sim.schedule={schedule}"]),
              reference,
              emit=lambda *_: None, render=False)
    _, got = load_npz(out / "result.npz", "result")
    _, want = load_npz(reference / "result.npz", "result")
    assert len(got["losses"]) == budget + 1
    assert np.array_equal(got["losses"], want["losses"])
    assert np.array_equal(got["controls"], want["controls"])
    assert np.array_equal(got["final_x"], want["final_x"])
