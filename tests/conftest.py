"""Shared test setup: Taichi on the CPU in float64, error measures, a small scene and random controls.

Kernels compile once per distinct State (about a second each, ten for the reverse step), so tests build
few simulators and share them through module-scoped fixtures.
"""
import os

import numpy as np
import pytest

import mls_mpm
from mls_mpm import runtime
from mls_mpm.grid import grid_op


@pytest.fixture(scope="session", autouse=True)
def taichi_f64():
    """Initialise Taichi once for the whole session: CPU, float64, fast_math off (runtime.ensure)."""
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))
    yield


@pytest.fixture(scope="module")
def taichi_f64_module():
    """Float64 again at the start of a module (use with pytestmark = pytest.mark.usefixtures(...)): a module
    run earlier may have switched Taichi to float32, and kernels that use the default float type (the material
    kernels in the tests) would then silently compute in float32, or tests/test_tape3d.py may have left matrices
    scalarized (the manual kernels then compile ~3x slower). A no-op when Taichi is already plain float64."""
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"), tape=False)


# Taichi's IR optimizations off (mls_mpm.config.compile_mode; its default too, set here so that the suite keeps it
# whatever that default becomes) for this process and the CLIs and children it starts: kernels compile 3-7x faster,
# with the same results to the bit (tests/test_runtime.py checks that against the optimized build);
# `MLS_MPM_COMPILE=optimized pytest` runs the suite optimized
os.environ.setdefault("MLS_MPM_COMPILE", "fast")

TINY = 1e-30


def rel_err(a, b):
    """Symmetric relative error |a - b| / max(|a|, |b|, tiny); arrays are compared by their 2-norms."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape, f"shapes differ: {a.shape} vs {b.shape}"
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b)), "NaN or Inf in a compared value"
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), np.linalg.norm(b), TINY))


def max_rel_err(a, b, axis=-1):
    """Largest symmetric relative error over entries, each entry the vector along `axis`.

    For adjoints whose entries differ by orders of magnitude (near-empty grid nodes), where a norm over
    the whole array would hide an error in the small entries.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    assert a.shape == b.shape, f"shapes differ: {a.shape} vs {b.shape}"
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b)), "NaN or Inf in a compared value"
    if axis is None:
        num, na, nb = np.abs(a - b), np.abs(a), np.abs(b)
    else:
        num, na, nb = (np.linalg.norm(t, axis=axis) for t in (a - b, a, b))
    return float(np.max(num / np.maximum(np.maximum(na, nb), TINY)))


SCENE = dict(n_grid=32, steps=30, dt=1e-3, E=100.0, nu=0.2, density=1.0, gamma=2.0, gravity=(0.0, -9.8),
             boundary="slip", bound=3, stride=10, particles_per_cell=4, dtype="f64", arch="cpu")
# its 3D twin: a 16^3 grid, 12 steps (controls every 4), 2 particles per cell volume (~270 in the ball of blob)
SCENE_3D = {**SCENE, "dim": 3, "n_grid": 16, "steps": 12, "stride": 4, "particles_per_cell": 2,
            "gravity": (0.0, -9.8, 0.0)}


def scene_config(**changes):
    """The small test scene: 32x32 grid, 30 steps of dt = 1e-3, E = 100, slip walls, gravity, light drag; with
    dim=3 its 3D twin SCENE_3D (16^3 grid, 12 steps).

    Stable: dt = 1e-3 is a third of the CFL limit dx / sqrt((lam + 2 mu) / rho) ~ 3e-3 (asserted; ~6e-3 in 3D).
    """
    base = SCENE_3D if changes.get("dim") == 3 else SCENE
    cfg = mls_mpm.SimConfig(**{**base, **changes})
    assert cfg.dt < 0.5 * cfg.cfl_dt, f"test scene dt = {cfg.dt} is not well below the CFL limit {cfg.cfl_dt}"
    return cfg


def blob(n_grid=32, center=(0.5, 0.5), radius=0.15, particles_per_cell=4, seed=0):
    """A disk of particles, particles_per_cell jittered samples per cell (about 290 for the defaults)."""
    rng = np.random.default_rng(seed)
    dx = 1.0 / n_grid
    k = int(round(np.sqrt(particles_per_cell)))
    sub = (np.arange(k) + 0.5) / k
    cells = np.arange(n_grid)
    ci, cj, si, sj = np.meshgrid(cells, cells, sub, sub, indexing="ij")
    x = np.stack([(ci + si).ravel(), (cj + sj).ravel()], axis=1) * dx
    x += rng.uniform(-0.25, 0.25, x.shape) * dx / k
    keep = np.linalg.norm(x - np.asarray(center), axis=1) < radius
    return x[keep]


def ball(n_grid=16, center=(0.5, 0.5, 0.5), radius=0.16, particles_per_cell=2, seed=0):
    """A 3D ball of particles: particles_per_cell uniform random samples per cell volume (about 140 for the
    defaults, the 3D twin of blob). Radius 0.16 on the 16^3 grid keeps every stencil (and a motion of 0.3 cells)
    off the wall zone (bound = 3): a slip wall's mask switches where a velocity component changes sign, a kink
    that central differences would straddle when it is exactly zero (free fall along y)."""
    rng = np.random.default_rng(seed)
    dx = 1.0 / n_grid
    cells = np.stack(np.meshgrid(*[np.arange(n_grid)] * 3, indexing="ij"), -1).reshape(-1, 1, 3)
    x = ((cells + rng.uniform(0.0, 1.0, (len(cells), particles_per_cell, 3))) * dx).reshape(-1, 3)
    keep = np.linalg.norm(x - np.asarray(center), axis=1) < radius
    return x[keep]


def body(dim):
    """The test body of the small scene of that dimension: blob() in 2D, ball() in 3D."""
    return blob() if dim == 2 else ball()


def random_controls(shape, scale=0.05, seed=1):
    """Controls F_pc (K, N, 2, 2) with independent normal entries of standard deviation `scale`."""
    return scale * np.random.default_rng(seed).standard_normal(shape)


def random_unit(shape, seed):
    """A random direction of unit 2-norm, for directional finite differences."""
    d = np.random.default_rng(seed).standard_normal(shape)
    return d / np.linalg.norm(d)


class StopAt:
    """should_stop that turns true at its n-th call (gd calls it after each control step and after each temporal
    iteration; adam, positions and lbfgs after each step or iteration, right after its checkpoint)."""

    def __init__(self, n):
        self.n, self.calls = n, 0

    def __call__(self):
        self.calls += 1
        return self.calls >= self.n


def grid_velocity(sim, f):
    """Grid velocity v_i of step f of sim's last forward pass: recomputed from its stored m_i, p_i by the forward's
    own grid_op (eq 17, gravity, walls), since a Simulator keeps v_i in one slot that each step overwrites."""
    grid_op(sim.fields, f)
    return sim.fields.grid_v.to_numpy()[0]
