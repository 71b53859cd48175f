"""mls_mpm.sizes: the particle count is read by the kernels at run time and the particle fields hold a capacity of a
few sizes, so that a new shape of another count in the same capacity reuses the compiled kernels; the results are
those of fields of exactly N particles, to the bit."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mls_mpm
from conftest import ball, blob, random_controls, scene_config
from mls_mpm import memory
from mls_mpm.sizes import CAPACITY_STEPS, particle_capacity

pytestmark = pytest.mark.usefixtures("taichi_f64_module")
ROOT = Path(__file__).resolve().parents[1]


def test_capacity_holds_n_in_a_few_sizes_a_doubling():
    counts = np.arange(1, 70000)
    caps = np.array([particle_capacity(int(n)) for n in counts])
    assert np.all(caps >= counts)
    assert np.all(np.diff(caps) >= 0)  # a larger count never gets a smaller capacity
    big = counts >= 1024  # where the spread's few extra particles no longer dominate
    assert np.max(caps[big] / counts[big]) <= 2 ** (1 / CAPACITY_STEPS) + 48 / 1024
    for lo in (1024, 4096, 16384):  # CAPACITY_STEPS sizes a doubling
        assert len({particle_capacity(n) for n in range(lo + 1, 2 * lo + 1)}) == CAPACITY_STEPS


def test_no_capacity_puts_a_particles_steps_a_multiple_of_4_kib_apart():
    """A particle's entries of steps f and f + 1 (or f + 2) lie capacity * entry bytes apart: never within 256 bytes
    of a multiple of 4 KiB (the same L1 cache sets), for x, v (8, 12 bytes in f32; 16, 24 in f64) and C, F (16, 36;
    32, 72). A power of two, 16,384, is what the rule moves: it made the 3D backward 7-10% slower."""
    assert particle_capacity(16384) != 16384
    for cap in sorted({particle_capacity(n) for n in range(1, 300000, 37)}):
        for entry in (8, 12, 16, 24, 32, 36, 72):
            for steps in (1, 2):
                r = steps * cap * entry % 4096
                assert 256 <= r <= 4096 - 256, (cap, entry, steps)


def run(sim, controls):
    L = sim.forward(controls)
    grad = sim.backward()
    return [np.float64(L), grad, sim.grad_x0, sim.grad_v0] + list(sim.state(sim.cfg.steps).values())


def padded_everywhere(monkeypatch):
    """2D Simulators with fields of particle_capacity(N), as 3D ones have by default (2D kernels compile in a
    fraction of the 3D time: the mechanism is the same in both)."""
    monkeypatch.setattr(memory, "field_capacity", lambda dim, n: particle_capacity(n))


@pytest.mark.parametrize("schedule", ["serial", "parallel"])
def test_padded_fields_give_the_exact_fields_results_to_the_bit(schedule, monkeypatch):
    cfg = scene_config(schedule=schedule, threads=2, steps=12, stride=4)
    x0 = blob()
    N = len(x0)
    assert particle_capacity(N) > N  # the test needs padding
    rng = np.random.default_rng(3)
    loss = mls_mpm.MassLoss([rng.uniform(0, 1e-3, (32, 32))])
    controls = random_controls((cfg.n_controls, N, 2, 2), 0.05, seed=4)
    exact = mls_mpm.Simulator(cfg, x0, loss=loss)  # 2D: exactly N (sizes.field_capacity)
    padded_everywhere(monkeypatch)
    padded = mls_mpm.Simulator(cfg, x0, loss=loss)
    assert padded.fields.capacity == particle_capacity(N) and exact.fields.capacity == N
    assert (padded.fields.lanes > 0) == (schedule == "parallel")
    for a, b in zip(run(padded, controls), run(exact, controls)):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()


def test_3d_fields_hold_the_capacity_with_the_exact_fields_results(monkeypatch):
    cfg = scene_config(dim=3, steps=4, stride=2, schedule="serial")
    x0 = ball()
    N = len(x0)
    rng = np.random.default_rng(5)
    loss = mls_mpm.MassLoss([rng.uniform(0, 1e-3, (16, 16, 16))])
    controls = random_controls((cfg.n_controls, N, 3, 3), 0.05, seed=6)
    padded = mls_mpm.Simulator(cfg, x0, loss=loss)  # 3D: particle_capacity(N) (sizes.field_capacity)
    monkeypatch.setattr(memory, "field_capacity", lambda dim, n: n)
    exact = mls_mpm.Simulator(cfg, x0, loss=loss)
    assert padded.fields.capacity == particle_capacity(N) > N == exact.fields.capacity
    for a, b in zip(run(padded, controls), run(exact, controls)):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()


def test_a_fault_names_the_particle_in_padded_fields(monkeypatch):
    padded_everywhere(monkeypatch)
    cfg = scene_config(steps=6, stride=3)
    x0 = blob()
    sim = mls_mpm.Simulator(cfg, x0)
    assert sim.fields.capacity > len(x0)
    controls = np.zeros(sim.control_shape)
    controls[1, 123] = np.inf  # control 1 acts at step 3
    with pytest.raises(ValueError, match=r"control 1 \(step 3\), particle 123 holds NaN or Inf"):
        sim.forward(controls)
    controls[1, 123] = 1e200  # finite, but its stress overflows at step 3 (the fault code f N + p, N read at run time)
    with pytest.raises(mls_mpm.SimulationError, match="^step 3: particle 123 "):
        sim.forward(controls)


def test_memory_counts_the_capacity_and_falls_back_to_n_where_only_that_fits():
    N = 1100
    cap = particle_capacity(N)
    assert cap > N
    for dim, fields in ((2, N), (3, cap)):
        cfg = scene_config(dim=dim, steps=10)
        state = 2 * dim + 2 * dim * dim  # x, v, C, F
        parts = memory.parts(cfg, N)
        assert parts[0].field_bytes == (cfg.steps + 1) * fields * state * 8
        assert parts[0].what.endswith(f"x {N} particles")
        tape = memory.parts(cfg, N, tape=True)
        assert tape[0].field_bytes == 2 * (cfg.steps + 1) * N * state * 8  # the Tape's copy holds exactly N
    cfg = scene_config(dim=3, steps=10)
    exact, padded = (memory.estimate_bytes(cfg, N, capacity=c) for c in (N, cap))
    assert memory.check_memory(cfg, N) == cap
    between = cfg.replace(max_memory_gb=(exact + padded) / 2 / 2 ** 30)
    assert memory.check_memory(between, N) == N  # the padding is never the reason for a refusal
    with pytest.raises(mls_mpm.ConfigError, match="the simulation needs"):
        memory.check_memory(cfg.replace(max_memory_gb=0.9 * exact / 2 ** 30), N)


# Builds the test scene with the given particle count in a fresh process (the Taichi cache of the test), its fields
# of particle_capacity(N) as in 3D, runs a forward and backward pass, and prints the capacity.
CHILD = '''
import json, sys
import numpy as np
sys.path.insert(0, sys.argv[2])
import mls_mpm
from mls_mpm import memory
from mls_mpm.sizes import particle_capacity
from conftest import blob, scene_config
memory.field_capacity = lambda dim, n: particle_capacity(n)
n = int(sys.argv[1])
cfg = scene_config(schedule="serial", steps=6, stride=3)
x0 = blob(particles_per_cell=16)[:n]
loss = mls_mpm.MassLoss([np.full((32, 32), 1e-4)])
sim = mls_mpm.Simulator(cfg, x0, loss=loss)
sim.forward(np.zeros(sim.control_shape))
sim.backward()
print(json.dumps({"capacity": sim.fields.capacity}))
'''


def cached_kernels(tmp_path, n, cache):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TI_OFFLINE_CACHE_FILE_PATH": str(cache)}
    out = subprocess.run([sys.executable, "-c", CHILD, str(n), str(ROOT / "tests")], env=env, capture_output=True,
                         text=True, timeout=600, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    capacity = json.loads(out.stdout.strip().splitlines()[-1])["capacity"]
    return capacity, len(list(Path(cache).rglob("*.tic")))


def test_a_new_count_in_the_same_capacity_compiles_nothing(tmp_path):
    cache = tmp_path / "taichi_cache"
    first, kernels = cached_kernels(tmp_path, 1100, cache)
    assert kernels > 0
    again, same = cached_kernels(tmp_path, 1150, cache)  # another shape's count, the same capacity
    assert again == first == particle_capacity(1100) and same == kernels
    other, more = cached_kernels(tmp_path, 1000, cache)  # a count of the capacity below compiles its own
    assert other < first and more > kernels
