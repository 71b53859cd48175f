"""The GPU path: `sim.arch = gpu | vulkan | cuda` starts that backend or is refused, and on a Vulkan or CUDA device
the tiny scene (and a small 3D one) gives the CPU's results and the hand-written gradient passes `mls-mpm check`
there.

CI installs Mesa's lavapipe, a Vulkan driver that runs on the CPU (.ci/run), so Taichi's Vulkan code generation
(SPIR-V), its device memory and its host-device copies are exercised there; the Vulkan tests skip, saying so, on a
machine without any Vulkan driver. The CUDA tests skip on CI (no NVIDIA GPU) and run where one is lent
(benchmarks/gpu.sh). Each run is its own `mls-mpm` process: Taichi runs one backend per process.

Tolerances: results of the same scene on the device and on the CPU (losses of every iteration, the controls, the final
positions) agree to 1e-12 in float64 (measured 8e-16 on lavapipe: the same arithmetic in another order, through
float atomics) and 1e-5 in float32 (measured 5e-7); frames rendered from them differ by at most one level of 255 per
channel.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from conftest import rel_err
from mls_mpm import runtime
from mls_mpm.bench import backend_here
from mls_mpm.checkpoint import load_npz
from mls_mpm.runtime import ArchError

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "tiny.toml"


def mls_mpm(*args, env=None):
    return subprocess.run([sys.executable, "-m", "mls_mpm.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=600, env={**os.environ, **(env or {})})


def start_run(scene, out, arch, *sets, render=False):
    """`mls-mpm run` of scene into out on arch with `--set` of each of sets, started, not awaited (wait_all)."""
    args = ("run", scene, "--out", out, "--quiet", *(() if render else ("--no-render",)),
            *(arg for kv in (f"sim.arch={arch}", *sets) for arg in ("--set", kv)))
    return subprocess.Popen([sys.executable, "-m", "mls_mpm.cli", *map(str, args)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def wait_all(procs):
    for proc in procs:
        text, _ = proc.communicate(timeout=600)
        assert proc.returncode == 0, text


def same_results(gpu, cpu, device, tol):
    """The runs in folders gpu (on device) and cpu: each summary names its backend, and the losses of every
    iteration, the controls and the final positions agree within tol. Returns the device run's results."""
    assert json.loads((gpu / "summary.json").read_text())["backend"] == device
    assert json.loads((cpu / "summary.json").read_text())["backend"] == "cpu"
    _, got = load_npz(gpu / "result.npz", "result")
    _, want = load_npz(cpu / "result.npz", "result")
    assert got["losses"].shape == want["losses"].shape
    for key in ("losses", "controls", "final_x"):
        assert rel_err(got[key], want[key]) <= tol, key
    return got


# ---------------------------------------------------------------------------------------------------------
# No device: refused up front, one line, nothing written

@pytest.mark.parametrize("flags, arch", [(["--arch", "gpu"], "gpu"), (["--set", "sim.arch=vulkan"], "vulkan"),
                                         (["--set", "sim.arch=cuda"], "cuda")])
def test_missing_gpu_is_refused(tmp_path, flags, arch):
    """With no CUDA driver and the Vulkan loader pointed at a driver list that does not exist, a GPU run stops
    with exit 2 and one line naming sim.arch and what each backend needs, instead of Taichi's silent fallback to
    the CPU (vulkan, cuda) or its crash while probing OpenGL on a headless machine (gpu)."""
    if runtime._driver_present("cuda"):
        pytest.skip("a CUDA driver is installed here: sim.arch = gpu | cuda would run")
    out = tmp_path / "out"
    res = mls_mpm("run", TINY, "--out", out, *flags, env={"VK_ICD_FILENAMES": str(tmp_path / "no_driver.json")})
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"mls-mpm: error: sim.arch = {arch}: no ") and lines[0].endswith("use sim.arch = cpu")
    assert "needs an NVIDIA driver" in lines[0] or "needs a Vulkan driver" in lines[0]
    assert not out.exists()


# ---------------------------------------------------------------------------------------------------------
# A GPU: Vulkan (lavapipe on CI) and CUDA (where an NVIDIA GPU is lent; CI has none, so these skip there)

WHY_MISSING = {"vulkan": ".ci/run installs Mesa's lavapipe", "cuda": "CI has no NVIDIA GPU; benchmarks/gpu.sh runs "
               "these on one"}


@pytest.fixture(scope="module", params=["vulkan", "cuda"])
def device(request):
    """A GPU backend that starts here (its name), or the test skips, saying why."""
    try:
        assert backend_here(request.param) == request.param
    except ArchError as e:
        pytest.skip(f"no {request.param} device on this machine ({WHY_MISSING[request.param]}): {e}")
    return request.param


@pytest.fixture(scope="module")
def runs(device, tmp_path_factory):
    """The tiny scene on the CPU and on the device, float64 with frames and outlines, float32 without frames: the
    four runs at once (each compiles its kernels on one core)."""
    base = tmp_path_factory.mktemp(f"gpu_{device}")
    out, procs = {}, []
    for arch in ("cpu", device):
        for dtype in ("f64", "f32"):
            d = out[arch, dtype] = base / f"{arch}_{dtype}"
            # render.mp4 = false: ffmpeg encodes the same PNG frames on every backend (tests/test_video.py), and
            # imageio-ffmpeg (68 MB) does not fit the device tool's 64 MiB beside Taichi's wheel
            procs.append(start_run(TINY, d, arch, f"sim.dtype={dtype}", "render.outline=true", "render.mp4=false",
                                   render=dtype == "f64"))
    wait_all(procs)
    return out


@pytest.mark.parametrize("dtype, tol", [("f64", 1e-12), ("f32", 1e-5)])
def test_device_run_matches_cpu(device, runs, dtype, tol):
    got = same_results(runs[device, dtype], runs["cpu", dtype], device, tol)
    assert got["losses"][-1] < 0.6 * got["losses"][0]  # the optimization really ran on the device


def test_device_frames_match_cpu(device, runs):
    """Every frame and the sheet (mass field, body and target outlines by marching squares) as on the CPU."""
    gpu, cpu = runs[device, "f64"], runs["cpu", "f64"]
    names = sorted(str(p.relative_to(cpu)) for p in cpu.rglob("*.png"))
    assert "sheet.png" in names and len([n for n in names if n.startswith("frames/")]) == 5
    assert names == sorted(str(p.relative_to(gpu)) for p in gpu.rglob("*.png"))
    for name in names:
        a = np.asarray(Image.open(gpu / name).convert("RGB"), dtype=np.int16)
        b = np.asarray(Image.open(cpu / name).convert("RGB"), dtype=np.int16)
        assert a.shape == b.shape and np.abs(a - b).max() <= 1, name
        if name.startswith("frames/"):
            assert (b == 255).all(-1).mean() > 0.5 and (b != 255).any(-1).mean() > 0.05, name  # white around a body


def test_device_gradient_check(device):
    """`mls-mpm check` on the device: the hand-written gradient against ti.ad.Tape (1e-6) and FD (1e-5) there."""
    res = mls_mpm("check", TINY, "--set", f"sim.arch={device}")
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.rstrip().endswith("OK")


def test_device_gradient_check_3d(device):
    """`mls-mpm check` of a shipped 3D scene on CUDA (Tape 1e-6, FD 1e-5). On Vulkan it is refused up front, one line,
    exit 2: there Taichi 1.7.4's Tape of the 3D kernels disagreed with the manual gradient by 98% (lavapipe, 60
    particles, 4 steps) while the manual gradient matched central differences (4e-8) and the CPU's
    (test_device_3d_run_matches_cpu), so the check would have blamed the wrong gradient."""
    res = mls_mpm("check", ROOT / "scenes" / "sphere_to_torus_3d.toml", "--set", f"sim.arch={device}")
    if device == "vulkan":
        assert res.returncode == 2, res.stdout + res.stderr
        assert res.stderr.splitlines() == [
            "mls-mpm: error: check sphere_to_torus_3d: the ti.ad.Tape oracle gives wrong 3D gradients on Vulkan "
            "(Taichi 1.7.4; the manual gradient is right there, tests/test_gpu.py); run the check with --set "
            "sim.arch=cpu or cuda"]
        return
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.rstrip().endswith("OK")


@pytest.mark.parametrize("device", ["vulkan"], indirect=True)
def test_gradient_tape_refused_in_3d_on_vulkan(device):
    """Simulator.gradient_tape (the API, not only `mls-mpm check`) refuses the 3D Tape on Vulkan with the reason,
    instead of returning its wrong gradient (see test_device_gradient_check_3d)."""
    code = ("import numpy as np\n"
            "from mls_mpm.config import ConfigError, SimConfig\n"
            "from mls_mpm.losses import MassLoss\n"
            "from mls_mpm.simulator import Simulator\n"
            f"cfg = SimConfig(dim=3, n_grid=16, steps=2, stride=1, dtype='f32', arch={device!r})\n"
            "x0 = 0.5 + 0.05 * np.random.default_rng(0).uniform(-1, 1, (20, 3))\n"
            "sim = Simulator(cfg, x0, loss=MassLoss([np.full((16, 16, 16), 1e-3)]))\n"
            "try:\n"
            "    sim.gradient_tape(sim.zero_controls())\n"
            "except ConfigError as e:\n"
            "    print('refused:', e)\n")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.splitlines()[-1] == (
        "refused: gradient_tape: the ti.ad.Tape oracle gives wrong 3D gradients on Vulkan (Taichi 1.7.4; the manual "
        "gradient is right there, tests/test_gpu.py); use sim.arch = cpu or cuda")


@pytest.mark.parametrize("dtype, tol", [("f64", 1e-12), ("f32", 1e-5)])
def test_device_3d_run_matches_cpu(device, dtype, tol, tmp_path):
    """A 3D scene (sphere_to_torus_3d on a 16^3 grid, 4 steps, one iteration) on the device and on the CPU: the same
    losses, controls and final positions, to the 2D run's tolerances. On Vulkan the 3D kernels failed to compile
    before kernels.axis0 indexed the stencil's weights by ti.select there (Taichi's SPIR-V code generator: 'Value
    "tmpN" does not yet exist'), and in float64 before material.inverse_cbrt took the polar decomposition's
    |det X|^(-1/3) without a 64-bit pow, which SPIR-V lacks (measured on lavapipe: 2.5e-16 in f64, 3e-7 in f32).
    Lavapipe compiles each in about a minute."""
    sets = (f"sim.dtype={dtype}", "sim.n_grid=16", "sim.steps=4", "control.stride=2", "optimize.iterations=1",
            "loss.grids=[16]")
    scene = ROOT / "scenes" / "sphere_to_torus_3d.toml"
    wait_all([start_run(scene, tmp_path / arch, arch, *sets) for arch in ("cpu", device)])
    got = same_results(tmp_path / device, tmp_path / "cpu", device, tol)
    assert got["controls"].shape[-2:] == (3, 3)
    assert np.abs(got["controls"]).max() > 0  # the gradient step really ran on the device


def test_f64_log_on_the_device(device, tmp_path):
    """Taichi's SPIR-V has no 64-bit log: the log mass loss in float64 is refused up front on Vulkan (one line, exit
    2, nothing written); CUDA has one, and the same run completes there."""
    out = tmp_path / "out"
    res = mls_mpm("run", TINY, "--out", out, "--quiet", "--no-render", "--set", f"sim.arch={device}", "--set",
                  "loss.kind=log_mass")
    if device == "cuda":
        assert res.returncode == 0, res.stdout + res.stderr
        assert json.loads((out / "summary.json").read_text())["backend"] == "cuda"
        return
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.splitlines()
    assert lines == ["mls-mpm: error: loss.kind = log_mass needs a 64-bit log, which Taichi's Vulkan backend cannot "
                     "compile; use sim.dtype = f32, loss.kind = mass, or sim.arch = cpu or cuda"]
    assert not out.exists()
