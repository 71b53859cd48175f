"""The Taichi runtime is explicit: one TaichiRuntime owns its settings and a generation number; re-initialising
(another dtype, arch or thread count) bumps the generation, and a Simulator built before refuses to run with
one line instead of touching freed fields (a bare AssertionError before). Only cheap kernels run here
(write_step, read_step): no step is compiled."""
import json
import os
import subprocess
import sys
from pathlib import Path

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
    mode = "" if RUNTIME.settings.optimized else ", fast compile"  # MLS_MPM_COMPILE (conftest: fast)
    old = f"f64 on cpu with {threads} thread{'s' if threads != 1 else ''}{mode}"
    sim32 = mls_mpm.Simulator(config(dtype="f32"), x0)
    assert RUNTIME.settings.dtype == "f32"
    msg = (f"^this Simulator was built for {old}; Taichi has since been re-initialised for f32 on cpu with "
           f"{threads} thread{'s' if threads != 1 else ''}{mode}, which freed its fields; build a new Simulator$")
    calls = [lambda: sim.forward(sim.zero_controls()), lambda: sim.backward(), lambda: sim.grad_x0,
             lambda: sim.grad_v0, lambda: sim.state(0), lambda: sim.set_initial(x0),
             lambda: sim.evaluate_positions(x0), lambda: sim.gradient_tape(sim.zero_controls())]
    for call in calls:
        with pytest.raises(StaleSimulatorError, match=msg):
            call()
    assert sim32.state(0)["x"].shape == x0.shape  # the new one works


def test_a_simulator_serves_only_its_own_settings_count_and_runtime():
    """Simulator.serves (render_run re-simulates a run with the run's own simulator): the same settings and particle
    count in the runtime it was built in; not after a re-initialisation, which freed its fields."""
    x0 = blob(n_grid=16, radius=0.2)
    sim = mls_mpm.Simulator(config(), x0)
    assert sim.serves(config(), len(x0))
    assert not sim.serves(config(dt=2e-3), len(x0))
    assert not sim.serves(config(), len(x0) - 1)
    mls_mpm.Simulator(config(dtype="f32"), x0)  # re-initialises Taichi
    assert not sim.serves(config(), len(x0))


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
                       match="built for f64 on cpu with 1 thread(, fast compile)?; .* for f64 on cpu with 2 threads"):
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


@pytest.mark.parametrize("dim, n_grid, particles, threads, pinned, serial", [
    (2, 64, 1600, 2, False, True),  # 2D on 2 threads: serial measured faster up to 5,696 particles + nodes
    (2, 64, 4000, 2, False, False),  # 8,096: the parallel schedule, each pass in one launch, measured faster
    (2, 64, 1600, 2, True, False),  # the 2 threads pinned to the 2 CPUs: parallel from SERIAL_BELOW_2D_PINNED
    (2, 32, 1245, 2, True, False),  # the f64 thesis size (2,269 units): parallel measured 1.48x faster pinned
    (2, 32, 1245, 2, False, True),
    (2, 16, 100, 2, True, True),  # 356 units: below the pinned floor, serial
    (2, 128, 64000, 1, False, True),  # one thread: always serial
    (3, 64, 100000, 1, False, True),
    (2, 128, 32000, 2, False, False),  # 16,384 nodes + 32,000 particles: past SERIAL_BELOW_2D_TWO_THREADS
    (2, 256, 64000, 2, False, False),
    (2, 64, 8192, 4, False, False),  # more threads: the general SERIAL_BELOW (4,000 particles + nodes)
    (2, 32, 1000, 8, False, True),
    (2, 32, 1000, 4, True, True),  # pinned, but more than 2 threads: SERIAL_BELOW, as unmeasured
    (3, 32, 17157, 2, False, False),  # 3D: the parallel schedule measured faster (17k particles, 32^3)
    (3, 12, 300, 2, False, True),
    (3, 12, 300, 2, True, True),  # 3D pinned keeps SERIAL_BELOW
])
def test_auto_schedule_choice(monkeypatch, dim, n_grid, particles, threads, pinned, serial):
    monkeypatch.setattr(mls_mpm.config, "pins_workers", lambda t: pinned)  # not this machine's CPU count
    cfg = mls_mpm.SimConfig(dim=dim, n_grid=n_grid, threads=threads)
    assert cfg.serial(particles) is serial
    assert cfg.lanes(particles) == (0 if serial else threads)
    assert mls_mpm.SimConfig(dim=dim, n_grid=n_grid, threads=threads, schedule="parallel").serial(particles) is False


def test_pins_workers_only_when_threads_fill_the_cpus():
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 0
    assert mls_mpm.config.pins_workers(1) is False  # one thread: nothing to place
    assert mls_mpm.config.pins_workers(cpus + 1) is False
    if cpus >= 2 and os.path.isdir("/proc/self/task"):
        assert mls_mpm.config.pins_workers(cpus) is True


MODES_SCRIPT = r"""
import sys

import numpy as np

import mls_mpm
from conftest import body, random_controls, scene_config
from mls_mpm.runtime import RUNTIME

out = {}
for case, dim, dtype, schedule in (("2", 2, "f64", "serial"), ("2 f32", 2, "f32", "parallel")):
    cfg = scene_config(dim=dim, dtype=dtype, schedule=schedule)
    res = 16 if dim == 2 else 8
    sim = mls_mpm.Simulator(cfg, body(dim), loss=mls_mpm.MassLoss([np.full((res,) * dim, 0.5 / res ** dim)]))
    c = random_controls(sim.control_shape, 0.05, seed=3)
    out[f"loss {case}"] = sim.forward(c)
    out.update({f"{key} {case}": value for key, value in sim.state(cfg.steps).items()})
    out[f"grad {case}"] = sim.backward()
    out[f"grad_x0 {case}"] = sim.grad_x0
    out[f"schedule {case}"] = "serial" if sim._serial else "parallel"
    out[f"optimized {case}"] = RUNTIME.settings.optimized
np.savez(sys.argv[1], **out)
"""


def test_fast_compile_gives_the_optimized_results_to_the_bit(tmp_path):
    """MLS_MPM_COMPILE=fast (the default, and what this suite runs under, conftest) against the optimized build: the
    small 2D test scene (float64 on the serial schedule, float32 on the parallel), run in two child processes side by
    side, gives the same final state, loss, dL/dF_pc and dL/dx0 to the bit, so the suite's verdicts hold for those who
    opt in to the optimized build. In 3D the optimized compile alone takes 2-3 minutes on 2 cores: there
    benchmarks/compile_modes.py compares the modes' results (its column "results"; BENCHMARKS.md "Compile time")."""
    script = tmp_path / "modes.py"
    script.write_text(MODES_SCRIPT)
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), str(root / "tests")])}
    children = {mode: subprocess.Popen([sys.executable, str(script), str(tmp_path / f"{mode}.npz")],
                                       env={**env, "MLS_MPM_COMPILE": mode}, stderr=subprocess.PIPE, text=True)
                for mode in ("optimized", "fast")}
    for mode, child in children.items():
        _, err = child.communicate(timeout=900)
        assert child.returncode == 0, f"{mode}: {err[-2000:]}"
    opt, fast = (np.load(tmp_path / f"{mode}.npz") for mode in ("optimized", "fast"))
    assert all(opt[f"optimized {case}"] and not fast[f"optimized {case}"] for case in ("2", "2 f32"))
    assert [str(opt[f"schedule {case}"]) for case in ("2", "2 f32")] == ["serial", "parallel"]
    assert sorted(opt.files) == sorted(fast.files)
    for key in opt.files:
        if not key.startswith("optimized"):
            assert np.array_equal(opt[key], fast[key]), f"{key}: differs between the compile modes"
    for case in ("2", "2 f32"):
        assert np.all(np.isfinite(fast[f"grad {case}"])) and np.any(fast[f"grad {case}"] != 0.0)


def test_the_cpu_compiles_fast_unless_told_otherwise(monkeypatch):
    """Without MLS_MPM_COMPILE the CPU compiles without Taichi's IR optimizations (config.compile_mode: a new shape's
    kernels compile 3-7x faster); MLS_MPM_COMPILE=optimized turns them on; a GPU always has them."""
    monkeypatch.delenv("MLS_MPM_COMPILE", raising=False)
    assert mls_mpm.config.compile_mode() == "fast"
    assert runtime.wants_optimized("cpu") is False and runtime.wants_optimized("cuda") is True
    monkeypatch.setenv("MLS_MPM_COMPILE", "")  # set but empty: the default too
    assert mls_mpm.config.compile_mode() == "fast"
    monkeypatch.setenv("MLS_MPM_COMPILE", "optimized")
    assert runtime.wants_optimized("cpu") is True and runtime.wants_optimized("vulkan") is True


def test_an_unknown_compile_mode_is_refused_in_one_line(monkeypatch):
    monkeypatch.setenv("MLS_MPM_COMPILE", "quick")
    with pytest.raises(runtime.UserError,
                       match="^environment variable MLS_MPM_COMPILE = 'quick': expected one of optimized, fast$"):
        runtime.ensure(config(dtype="f32"))


def test_a_float32_tape_is_right_whatever_the_compile_mode():
    """Taichi 1.7.4's Tape compiled without its IR optimizations gives a zero gradient in float32, so on a runtime
    compiled fast (this suite's) gradient_tape of a float32 Simulator runs in a child process that compiles it
    optimized: the Simulator keeps its fields (no re-initialisation here) and the Tape matches backward()."""
    x0 = blob(n_grid=16, radius=0.2)
    sim = mls_mpm.Simulator(config(dtype="f32", steps=6, stride=3), x0, loss=mls_mpm.PositionLoss(x0 + 0.01))
    generation = RUNTIME.generation
    c = 0.05 * np.random.default_rng(0).standard_normal(sim.control_shape)
    sim.forward(c)
    g = sim.backward()
    g_tape = sim.gradient_tape(c)
    assert RUNTIME.generation == generation and RUNTIME.settings.dtype == "f32"
    assert np.linalg.norm(g) > 0 and np.linalg.norm(g_tape - g) <= 1e-4 * np.linalg.norm(g)
    assert np.array_equal(sim.backward(), g)  # the Simulator still runs


BLAS_SCRIPT = """
import json, os, sys
import numpy as np
from threadpoolctl import threadpool_info, threadpool_limits
threadpool_limits(limits=2, user_api="blas")  # what a user's process may have set
before = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
import mls_mpm
from mls_mpm import runtime
runtime.ensure(mls_mpm.SimConfig(n_grid=16, steps=4, stride=2, dt=1e-3, E=100.0))
after = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
print(json.dumps({"before": before, "after": after, "env": os.environ.get("OPENBLAS_NUM_THREADS")}))
"""


def test_starting_taichi_puts_numpys_blas_on_one_thread(tmp_path):
    """mls_mpm.blas: OpenBLAS's threads spinning after an L-BFGS or transport-loss call slowed the next passes 1.4-1.9x
    on 2 CPUs. A fresh process whose BLAS a user set to 2 threads runs it on one once Taichi is started, and its
    children (OPENBLAS_NUM_THREADS) start so."""
    script = tmp_path / "blas.py"
    script.write_text(BLAS_SCRIPT)
    root = Path(__file__).resolve().parents[1]
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300,
                         env={**env, "PYTHONPATH": str(root)})
    assert res.returncode == 0, res.stderr[-2000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["before"], "numpy has no BLAS that threadpoolctl sees"
    assert max(out["before"]) == 2 or default_threads() == 1  # OpenBLAS caps its threads at the CPUs
    assert out["after"] == [1] * len(out["after"]) and out["env"] == "1"


def test_the_runtime_of_this_process_keeps_blas_on_one_thread():
    from threadpoolctl import threadpool_info

    pools = [pool for pool in threadpool_info() if pool["user_api"] == "blas"]
    assert pools and all(pool["num_threads"] == 1 for pool in pools)
