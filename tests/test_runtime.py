"""The Taichi runtime is explicit: one TaichiRuntime owns its settings and a generation number; re-initialising
(another dtype, arch or thread count) bumps the generation, and a Simulator built before refuses to run with
one line instead of touching freed fields (a bare AssertionError before). Only cheap kernels run here
(write_step, read_step): no step is compiled."""
import os

import numpy as np
import pytest
import taichi as ti
from taichi.lang import impl

import mls_mpm
from conftest import blob
from mls_mpm import runtime
from mls_mpm.config import default_threads
from mls_mpm.runtime import RUNTIME, StaleSimulatorError


@pytest.fixture(autouse=True)
def back_to_the_default():
    """Each test starts and ends on the suite's runtime (f64, CPU, default threads)."""
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))
    yield
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))


def config(**changes):
    return mls_mpm.SimConfig(**{**dict(n_grid=16, steps=4, stride=2, dt=1e-3, E=100.0, schedule="parallel"),
                                **changes})


def test_default_threads_are_the_cores_this_process_may_use():
    expected = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert default_threads() == expected
    assert mls_mpm.SimConfig().cpu_threads == expected
    assert impl.current_cfg().cpu_max_num_threads == expected == RUNTIME.settings.threads


def test_same_settings_keep_the_generation():
    g = runtime.ensure(config())
    assert runtime.ensure(config(threads=default_threads())) == g
    sim = mls_mpm.Simulator(config(), blob(n_grid=16, radius=0.2))
    assert runtime.ensure(config()) == g
    assert sim.state(0)["x"].shape == (sim.n_particles, 2)


def test_a_simulator_of_an_older_runtime_refuses_to_run():
    x0 = blob(n_grid=16, radius=0.2)
    sim = mls_mpm.Simulator(config(), x0, loss=mls_mpm.MassLoss([np.zeros((16, 16))]))
    threads = default_threads()
    old = f"f64 on cpu with {threads} thread{'s' if threads != 1 else ''}"
    sim32 = mls_mpm.Simulator(config(dtype="f32"), x0)
    assert RUNTIME.settings.dtype == "f32"
    msg = (f"^this Simulator was built for {old}; Taichi has since been re-initialised for f32 on cpu with "
           f"{threads} thread{'s' if threads != 1 else ''}, which freed its fields; build a new Simulator$")
    calls = [lambda: sim.forward(sim.zero_controls()), lambda: sim.backward(), lambda: sim.grad_x0,
             lambda: sim.grad_v0, lambda: sim.state(0), lambda: sim.set_initial(x0),
             lambda: sim.evaluate_positions(x0), lambda: sim.gradient_tape(sim.zero_controls())]
    for call in calls:
        with pytest.raises(StaleSimulatorError, match=msg):
            call()
    assert sim32.state(0)["x"].shape == x0.shape  # the new one works


def test_threads_that_differ_from_taichis_reinitialise():
    """threads = 1 after Taichi started with the default: Taichi runs 1 thread and the lanes match it."""
    before = RUNTIME.generation
    sim = mls_mpm.Simulator(config(threads=1), blob(n_grid=16, radius=0.2))
    assert RUNTIME.generation == before + 1
    assert impl.current_cfg().cpu_max_num_threads == 1 == RUNTIME.settings.threads
    assert sim.fields.lanes == 1
    two = mls_mpm.Simulator(config(threads=2), blob(n_grid=16, radius=0.2))
    assert impl.current_cfg().cpu_max_num_threads == 2 and two.fields.lanes == 2
    with pytest.raises(StaleSimulatorError,
                       match="built for f64 on cpu with 1 thread; .* for f64 on cpu with 2 threads"):
        sim.state(0)


def test_a_reset_outside_the_runtime_is_seen():
    """ti.reset() / ti.init() called directly still invalidates the Simulators built before."""
    sim = mls_mpm.Simulator(config(), blob(n_grid=16, radius=0.2))
    ti.reset()
    with pytest.raises(StaleSimulatorError, match="^this Simulator was built for f64 on cpu with .*; Taichi has since "
                                                  "been reset, which freed its fields; build a new Simulator$"):
        sim.state(0)
    ti.init(arch=ti.cpu, default_fp=ti.f64, log_level=ti.ERROR)
    with pytest.raises(StaleSimulatorError, match="re-initialised for f64 on cpu"):
        sim.state(0)


@pytest.mark.parametrize("dim, n_grid, particles, threads, serial", [
    (2, 64, 8192, 2, True),  # 2D on 2 threads: serial measured faster up to 64k particles (BENCHMARKS.md)
    (2, 128, 64000, 1, True),
    (2, 256, 64000, 2, False),  # 65,536 nodes + 64,000 particles: past SERIAL_BELOW_2D_TWO_THREADS
    (2, 64, 8192, 4, False),  # more threads: the general SERIAL_BELOW (4,000 particles + nodes)
    (2, 32, 1000, 8, True),
    (3, 32, 17157, 2, False),  # 3D: the parallel schedule measured faster (17k particles, 32^3)
    (3, 12, 300, 2, True),
])
def test_auto_schedule_choice(dim, n_grid, particles, threads, serial):
    cfg = mls_mpm.SimConfig(dim=dim, n_grid=n_grid, threads=threads)
    assert cfg.serial(particles) is serial
    assert cfg.lanes(particles) == (0 if serial else threads)
    assert mls_mpm.SimConfig(dim=dim, n_grid=n_grid, threads=threads, schedule="parallel").serial(particles) is False
