"""The GPU path: `sim.arch = gpu | vulkan | cuda` starts that backend or is refused, and on a Vulkan device the tiny
scene gives the CPU's results.

CI installs Mesa's lavapipe, a Vulkan driver that runs on the CPU (.ci/run), so Taichi's Vulkan code generation
(SPIR-V), its device memory and its host-device copies are exercised there; the Vulkan tests skip, saying so, on a
machine without any Vulkan driver. Each run is its own `mls-mpm` process: Taichi runs one backend per process.

Tolerances: results of the same scene on Vulkan and on the CPU (losses of every iteration, the controls, the final
positions) agree to 1e-12 in float64 (measured 8e-16: the same arithmetic in another order, through float atomics)
and 1e-5 in float32 (measured 5e-7); frames rendered from them differ by at most one level of 255 per channel.
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
# A Vulkan device

@pytest.fixture(scope="module")
def vulkan():
    try:
        assert backend_here("vulkan") == "vulkan"
    except ArchError as e:
        pytest.skip(f"no Vulkan device on this machine (.ci/run installs Mesa's lavapipe): {e}")


@pytest.fixture(scope="module")
def runs(vulkan, tmp_path_factory):
    """The tiny scene on the CPU and on Vulkan, float64 with frames and outlines, float32 without frames."""
    base = tmp_path_factory.mktemp("gpu")
    out = {}
    for arch in ("cpu", "vulkan"):
        for dtype in ("f64", "f32"):
            d = base / f"{arch}_{dtype}"
            res = mls_mpm("run", TINY, "--out", d, "--quiet", "--set", f"sim.arch={arch}", "--set", f"sim.dtype={dtype}",
                          "--set", "render.outline=true", *(["--no-render"] if dtype == "f32" else []))
            assert res.returncode == 0, res.stdout + res.stderr
            out[arch, dtype] = d
    return out


@pytest.mark.parametrize("dtype, tol", [("f64", 1e-12), ("f32", 1e-5)])
def test_vulkan_run_matches_cpu(runs, dtype, tol):
    gpu, cpu = runs["vulkan", dtype], runs["cpu", dtype]
    assert json.loads((gpu / "summary.json").read_text())["backend"] == "vulkan"
    assert json.loads((cpu / "summary.json").read_text())["backend"] == "cpu"
    _, got = load_npz(gpu / "result.npz", "result")
    _, want = load_npz(cpu / "result.npz", "result")
    assert got["losses"].shape == want["losses"].shape
    for key in ("losses", "controls", "final_x"):
        assert rel_err(got[key], want[key]) <= tol, key
    assert got["losses"][-1] < 0.6 * got["losses"][0]  # the optimization really ran on the device


def test_vulkan_frames_match_cpu(runs):
    """Every frame and the sheet (mass field, body and target outlines by marching squares) as on the CPU."""
    gpu, cpu = runs["vulkan", "f64"], runs["cpu", "f64"]
    names = sorted(str(p.relative_to(cpu)) for p in cpu.rglob("*.png"))
    assert "sheet.png" in names and len([n for n in names if n.startswith("frames/")]) == 5
    assert names == sorted(str(p.relative_to(gpu)) for p in gpu.rglob("*.png"))
    for name in names:
        a = np.asarray(Image.open(gpu / name).convert("RGB"), dtype=np.int16)
        b = np.asarray(Image.open(cpu / name).convert("RGB"), dtype=np.int16)
        assert a.shape == b.shape and np.abs(a - b).max() <= 1, name
        if name.startswith("frames/"):
            assert (b == 255).all(-1).mean() > 0.5 and (b != 255).any(-1).mean() > 0.05, name  # white around a body


def test_vulkan_gradient_check(vulkan):
    """`mls-mpm check` on Vulkan: the hand-written gradient against ti.ad.Tape (1e-6) and FD (1e-5) there."""
    res = mls_mpm("check", TINY, "--set", "sim.arch=vulkan")
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout.rstrip().endswith("OK")


def test_vulkan_refuses_f64_log(vulkan, tmp_path):
    """Taichi's SPIR-V has no 64-bit log: the log mass loss in float64 is refused up front on Vulkan."""
    out = tmp_path / "out"
    res = mls_mpm("run", TINY, "--out", out, "--set", "sim.arch=vulkan", "--set", "loss.kind=log_mass")
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.splitlines()
    assert lines == ["mls-mpm: error: loss.kind = log_mass needs a 64-bit log, which Taichi's Vulkan backend cannot "
                     "compile; use sim.dtype = f32, loss.kind = mass, or sim.arch = cpu or cuda"]
    assert not out.exists()
