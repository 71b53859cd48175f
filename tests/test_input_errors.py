"""Bad input end to end: each refusal is one line on stderr (`mls-mpm: error: ...`), exit 2, nothing written,
and the same refusal at the function level: scene files, images, memory before sampling, `check` options.
Also `check`'s round-off floor (a single particle's gradient of 1e-19 against a finite difference of 0)."""
import argparse
import os
import re
from pathlib import Path

import pytest

from mls_mpm import memory, problem
from mls_mpm.check import CheckError, Comparison, check_scene
from mls_mpm.cli import main
from mls_mpm.errors import UserError
from mls_mpm.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.toml"


def refused(capsys, tmp_path, *argv):
    """Run `mls-mpm argv` in tmp_path; assert exit 2, one stderr line, nothing written; return the message."""
    before = sorted(p for p in tmp_path.rglob("*"))
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        code = main([str(a) for a in argv])
    finally:
        os.chdir(cwd)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("mls-mpm: error: ") and err.count("\n") == 1, err
    assert sorted(p for p in tmp_path.rglob("*")) == before
    return err[len("mls-mpm: error: "):].rstrip("\n")


@pytest.fixture
def scene(tmp_path):
    """tests/data/tiny.toml copied into tmp_path (its images by absolute path)."""
    text = TINY.read_text().replace("../../scenes/images", str(ROOT / "scenes" / "images"))
    path = tmp_path / "tiny.toml"
    path.write_text(text)
    return path


# ---- scene files -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("setting, pattern", [
    ('scene.name=".."', r'scene\.name = "\.\." \(from --set\): expected a name of letters'),
    ('scene.name="../../x"', r'scene\.name = "\.\./\.\./x" \(from --set\): expected a name of letters'),
    ("render.size=100000", r"render\.size = 100000 \(from --set\): expected an integer in \[16, 8192\]"),
    ('render.mode="volume"', r'render\.mode = "volume" \(from --set\): expected one of "mass", "color", "particles" '
                             r'with sim\.dim = 2 \("surface", "volume": 3D runs only\)$'),
    ('render.background="black"', r'render\.background = "black" \(from --set\): expected one of "white", '
                                  r'"transparent"$'),
    ("sim.particles_per_cell=1000000000000000000000000000000", r"sim\.particles_per_cell = 10{30} \(from --set\): "
                                                                r"expected an integer in \[1, 1024\]"),
    ("sim.threads=1000000000000000000000000000000", r"sim\.threads = 10{30} \(from --set\): expected an integer in "
                                                    r"\[0, 1024\]"),
    ("sim.stride=5", r"sim\.stride = 5 \(from --set\): unknown key in \[sim\]; did you mean 'control\.stride'\?"),
    ("sim.dt=1979-05-27", r"sim\.dt = 1979-05-27 \(from --set\): expected a number > 0$"),
    ("sim.dt=0.019", r"sim\.dt = 0\.019 \(from --set\): expected at most the CFL limit dx / wave speed = "
                     r"0\.018\d+ for these n_grid, E, nu and density$"),
])
def test_run_refuses_bad_settings_in_one_line(capsys, tmp_path, scene, setting, pattern):
    message = refused(capsys, tmp_path, "run", scene, "--set", setting, "--no-render")
    assert message.startswith(f"{scene}: ") and re.search(pattern, message), message


def test_byte_order_mark_runs_through_load(tmp_path, scene):
    scene.write_bytes(b"\xef\xbb\xbf" + scene.read_bytes())
    assert load_scene(scene).name == "tiny"


# ---- images ------------------------------------------------------------------------------------------------

def huge_png(path, width, height):
    """A PNG header claiming width x height pixels (no pixel data)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IEND", b""))
    return path


@pytest.mark.parametrize("make, reason", [
    (lambda tmp: huge_png(tmp / "huge.png", 100000, 100000),
     r"the image is 100000 x 100000 = 1e\+04 megapixels, above the limit of 50 megapixels"),
    (lambda tmp: huge_png(tmp / "big.png", 20000, 20000),
     r"the image is 20000 x 20000 = 400 megapixels, above the limit of 50 megapixels"),
    (lambda tmp: (tmp / "dir.png").mkdir() or tmp / "dir.png", r"is a directory; expected an image file"),
    (lambda tmp: Path("/dev/zero"), r"is not a regular file \(a device, pipe or socket\); expected an image file"),
])
def test_run_refuses_bad_images_in_one_line(capsys, tmp_path, scene, make, reason):
    image = make(tmp_path)
    message = refused(capsys, tmp_path, "run", scene, "--set", f'scene.target="{image}"', "--no-render")
    assert message.startswith(f'{scene}: scene.target = "{image}" (from --set): expected an image file ({image}: ')
    assert re.search(reason, message), message


# ---- memory before sampling --------------------------------------------------------------------------------

@pytest.fixture
def little_memory(monkeypatch):
    """Pretend 2 GiB are available, whatever the machine has."""
    monkeypatch.setattr(memory, "available_bytes", lambda: 2 * 2 ** 30)


def never_sample(*_args, **_kwargs):
    raise AssertionError("sampled particles before the memory check")


@pytest.mark.parametrize("settings, pattern", [
    (["loss.grids=[100000]"], r"loss\.grids = \[100000\]: expected loss grids whose target arrays fit in memory "
                              r"\(about \d+ GiB for 100000\^2 nodes\), below the limit of 1\.8 GiB"),
    (["loss.grids=[16, 20000]"], r"loss\.grids = \[16, 20000\]: expected loss grids whose target arrays fit"),
    (["sim.n_grid=40000", "sim.dt=1e-5"], r"loss\.grids = \[40000\] \(sim\.n_grid when loss\.grids is not set\): "
                                          r"expected loss grids whose target arrays fit"),
    (["sim.n_grid=40000", "sim.dt=1e-5", "loss.grids=[16]"],
     r"sim\.n_grid = 40000, sim\.particles_per_cell = 4: expected particles that fit in memory \(up to \d+, about "
     r"[\d.]+ GiB while sampled\), below the limit of 1\.8 GiB \(90% of the memory available; sim\.max_memory_gb sets "
     r"it\); lower sim\.n_grid or sim\.particles_per_cell$"),
    (["loss.grids=[2000]", "sim.max_memory_gb=0.01"], r"loss\.grids = \[2000\]: expected loss grids whose target "
                                                       r"arrays fit .*, below the limit of 0\.01 GiB "
                                                       r"\(sim\.max_memory_gb = 0\.01\)$"),
    (["sim.n_grid=4096", "sim.dt=1e-4"], r"GiB"),  # the particles fit while sampled; the simulator's fields do not
])
def test_memory_refused_before_sampling(capsys, tmp_path, scene, little_memory, monkeypatch, settings, pattern):
    monkeypatch.setattr(problem, "sample_particles", never_sample)
    argv = [a for setting in settings for a in ("--set", setting)]
    message = refused(capsys, tmp_path, "run", scene, *argv, "--no-render")
    assert message.startswith(f"{scene}: ") and re.search(pattern, message), message
    with pytest.raises(UserError) as e:
        problem.build(load_scene(scene, settings))
    assert str(e.value) == message


def test_memory_check_gets_the_particle_bound_and_the_loss_grids(scene, monkeypatch):
    """check_memory is called before sampling with an upper bound of the particles and every loss grid."""
    calls = []
    monkeypatch.setattr(problem, "check_memory", lambda cfg, n, grids=(), where="": calls.append((n, grids, where)))
    s = load_scene(scene, ["loss.grids=[16, 32]"])
    p = problem.build(s)
    [(n, grids, where)] = calls
    assert len(p.x0) <= n <= 1.6 * len(p.x0)
    assert grids == [(16, 1, False), (32, 1, False)] and where == f"{scene}: "
    calls.clear()
    problem.build(load_scene(scene, ['loss.kind="color"', "loss.grids=[16]"]))
    assert calls[0][1] == [(16, 3, False)]
    calls.clear()
    problem.build(load_scene(scene, ["loss.penalty=10"]))
    assert calls[0][1] == [(32, 1, True)]


# ---- check -------------------------------------------------------------------------------------------------

def options(**changes):
    values = dict(steps=12, particles=300, tol_tape=1e-6, tol_fd=1e-5)
    values.update(changes)
    return argparse.Namespace(**values)


@pytest.mark.parametrize("changes, message", [
    (dict(particles=0), "check --particles 0: expected an integer >= 1"),
    (dict(particles=-3), "check --particles -3: expected an integer >= 1"),
    (dict(steps=0), "check --steps 0: expected an integer >= 1"),
    (dict(tol_tape=float("nan")), "check --tol-tape nan: expected a finite number > 0"),
    (dict(tol_tape=float("inf")), "check --tol-tape inf: expected a finite number > 0"),
    (dict(tol_fd=-1.0), "check --tol-fd -1.0: expected a finite number > 0"),
    (dict(tol_fd=0.0), "check --tol-fd 0.0: expected a finite number > 0"),
])
def test_check_refuses_bad_options(changes, message):
    with pytest.raises(CheckError) as e:
        check_scene(load_scene(TINY), options(**changes), emit=lambda *_: None)
    assert str(e.value) == message


@pytest.mark.parametrize("argv", [["--particles", "0"], ["--tol-tape", "nan"], ["--tol-fd", "-1"]])
def test_check_cli_refuses_bad_options(capsys, tmp_path, argv):
    code = main(["check", str(TINY), *argv])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and re.search(r"--particles|--tol-tape|--tol-fd", err), err


def test_comparison_floor():
    """Round-off-level differences pass whatever their relative error; larger ones need the tolerance."""
    tiny = Comparison.of([2e-19, -1e-19], [1e-19, 1e-19], floor=1e-15)
    assert tiny.rel > 0.5 and tiny.ok(1e-6) and tiny.by_floor(1e-6)
    real = Comparison.of([1.0, 2.0], [1.0, 2.0 + 1e-9], floor=1e-15)
    assert real.ok(1e-6) and not real.by_floor(1e-6) and not real.ok(1e-12)
    wrong = Comparison.of([1e-12], [0.0], floor=1e-15)
    assert not wrong.ok(1e-6)


def test_check_passes_a_particle_whose_gradient_is_round_off():
    """--particles 1 on tiny.toml: the one particle's controls barely reach the mass loss (gradient ~1e-19,
    finite differences exactly 0); both comparisons pass by the round-off floor and the floor is printed."""
    lines = []
    assert check_scene(load_scene(TINY), options(particles=1), emit=lines.append), lines
    assert "1 particles" in lines[0] and lines[-1] == "  OK"
    assert all("below the round-off floor" in line for line in lines[1:3]), lines
