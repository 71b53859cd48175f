"""Taichi's CPU worker threads pinned one to each CPU when the threads fill the process's CPUs (mls_mpm/affinity.py).

Each case runs in a fresh interpreter restricted to two CPUs before Taichi starts, so that the thread counts are the
same on any machine with at least two, and the test session's own Taichi runtime is left alone.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2
                                or not os.path.isdir("/proc/self/task"), reason="needs Linux and two CPUs")

CHILD = """
import json, os, sys, threading
cpus = sorted(os.sched_getaffinity(0))[:2]
os.sched_setaffinity(0, set(cpus))
import taichi as ti
from mls_mpm.config import SimConfig
from mls_mpm.runtime import RUNTIME, ensure

def cpu_ns():
    me = threading.get_native_id()
    return {int(t): int(open(f"/proc/self/task/{t}/schedstat").read().split()[0])
            for t in os.listdir("/proc/self/task") if int(t) != me}

ensure(SimConfig(dtype="f64", threads=int(sys.argv[1])))
out = ti.field(ti.f64, shape=1 << 16)

@ti.kernel
def busy():
    for i in range(1 << 22):  # thousands of tasks of 1024 items: every worker takes some
        out[i % (1 << 16)] = ti.sin(ti.cast(i, ti.f64) * 1e-3) + ti.cos(ti.cast(i, ti.f64) * 2e-3)

busy()  # compiled here (the compile threads work), measured below
before = cpu_ns()
busy()
after = cpu_ns()
print(json.dumps({"cpus": cpus, "pinned": {str(t): c for t, c in RUNTIME.pinned.items()},
                  "masks": {str(t): sorted(os.sched_getaffinity(t)) for t in after},
                  "ran": {str(t): after[t] - before.get(t, after[t]) for t in after}}))
"""


def child(tmp_path, threads):
    script = tmp_path / "child.py"  # a file, not -c: Taichi reads a kernel's source from its file
    script.write_text(CHILD)
    res = subprocess.run([sys.executable, str(script), str(threads)], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "TI_LOG_LEVEL": "error"}, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_workers_pinned_one_to_each_cpu_when_threads_fill_the_cpus(tmp_path):
    got = child(tmp_path, 2)
    pinned = got["pinned"]
    assert sorted(pinned.values()) == got["cpus"], got  # one worker on each of the two CPUs
    for tid, cpu in pinned.items():
        assert got["masks"][tid] == [cpu]
    others = [t for t in got["masks"] if t not in pinned]
    assert others, "Taichi starts compile threads besides its workers"
    for tid in others:  # the compile threads (and any library's threads) keep both CPUs
        assert got["masks"][tid] == got["cpus"], (tid, got)
    # the pinned threads are the ones that run a parallel kernel: each took a share of busy(), the others none
    worker_least = min(got["ran"][t] for t in pinned)
    assert worker_least > 0, got["ran"]
    assert max(got["ran"][t] for t in others) < 0.05 * worker_least, got["ran"]


def test_nothing_pinned_when_threads_do_not_match_the_cpus(tmp_path):
    got = child(tmp_path, 3)  # more threads than the two CPUs: no one-to-one placement exists
    assert got["pinned"] == {}
    assert all(mask == got["cpus"] for mask in got["masks"].values()), got["masks"]


SCHEDULE_CHILD = """
import json, os, sys
cpus = sorted(os.sched_getaffinity(0))[:2]
os.sched_setaffinity(0, set(cpus))
import numpy as np
import mls_mpm.affinity
from mls_mpm import SimConfig, Simulator
from mls_mpm.runtime import RUNTIME

if sys.argv[1] == "fails":  # the probe does not single out the workers (as affinity.find_workers can answer)
    mls_mpm.affinity.find_workers = lambda threads: None
cfg = SimConfig(dim=2, n_grid=32, steps=2, stride=1, dtype="f64", threads=2)
x0 = 0.3 + 0.4 * np.random.default_rng(0).random((1245, 2))  # the thesis size: 2,269 particles + nodes
sim = Simulator(cfg, x0)
print(json.dumps({"pinned": len(RUNTIME.pinned), "predicted_serial": cfg.serial(len(x0)),
                  "serial": sim._serial, "lanes": sim.fields.lanes}))
"""


@pytest.mark.parametrize("probe", ["works", "fails"])
def test_auto_schedule_does_not_follow_the_probe(tmp_path, probe):
    """`auto` runs 2D on 2 threads filling the 2 CPUs in parallel from SERIAL_BELOW_2D_PINNED whether or not the
    probe singled out the workers (it can fail on a busy machine): the schedule, and so the run's round-off, is the
    same in every run; a failed probe only leaves the threads unpinned."""
    script = tmp_path / "schedule.py"
    script.write_text(SCHEDULE_CHILD)
    res = subprocess.run([sys.executable, str(script), probe], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "TI_LOG_LEVEL": "error"}, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert got["predicted_serial"] is False, got  # before Taichi starts, config expects the pinning
    assert got == {"pinned": 2 if probe == "works" else 0, "predicted_serial": False, "serial": False, "lanes": 2}


def test_no_pinning_where_masks_cannot_be_set(monkeypatch):
    """config.pins_workers: where this process may not set a thread's CPUs (a sandbox), nothing is to be pinned, and
    `auto` keeps the unpinned threshold; where it may, 2 threads on 2 CPUs are."""
    import mls_mpm.config as config

    cpus = sorted(os.sched_getaffinity(0))[:2]
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(cpus))
    monkeypatch.setattr(os, "sched_setaffinity", lambda pid, mask: None)
    assert config.pins_workers(2) and not config.pins_workers(3)

    def refuse(pid, mask):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setaffinity", refuse)
    assert not config.pins_workers(2)
    cfg = config.SimConfig(dim=2, n_grid=32, steps=2, stride=1, dtype="f64", threads=2)
    assert cfg.serial(1245)  # 2,269 units: below SERIAL_BELOW_2D_TWO_THREADS
