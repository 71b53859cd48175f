"""Each of Taichi's CPU worker threads on a CPU of its own, when the threads fill every CPU this process may use.

The parallel schedule's passes run in one launch (persistent.py): each lane's thread works and meets the others at
spin barriers, so two lanes' threads on one CPU take turns by the scheduler's time slices. With as many threads as
CPUs, Linux often wakes both worker threads of a 2-CPU machine onto the same CPU (the one the launching thread is
not on) and only moves one of them later: the f64 thesis size (1,245 particles, 32^2) then ran its passes at
0.10 ms a step instead of 0.055, switching from pass to pass in one process, and the f32 64^2 / 8k forward at
0.29-0.37 instead of 0.28 (AMD EPYC, 2 CPUs; BENCHMARKS.md, "Worker threads pinned"). Pinning worker k to the k-th
allowed CPU removes this. With fewer threads than CPUs nothing is pinned: a woken thread then finds an idle CPU,
and other processes keep the CPUs the simulation does not ask for.

Taichi does not say which of its threads are the workers (it also starts compile threads): a probe launch holds
every worker in a lane task (state.LANE_TASK, as the lanes are run) for a millisecond or two, and the threads whose
CPU time grew by that much are the workers (/proc/self/task/*/schedstat).
"""
import os
import threading

import taichi as ti

from .config import pins_workers
from .state import LANE_TASK

HOLD_SPINS = 1 << 20  # atomic reads each worker spins once all have arrived (2-8 ms), far above any idle thread
WAIT_SPINS = 1 << 24  # give up waiting for the other workers after this many (fewer workers running than asked)
MIN_HELD_NS = 500_000  # CPU time a worker gains in the probe, at least
PROBE_TRIES = 3  # probes before the workers are left unpinned (a busy moment can hide one); each takes 2-8 ms


@ti.kernel
def hold_lanes(count: ti.template(), lanes: ti.i32, hold: ti.i32):
    """Each of `lanes` lane tasks arrives at count[None], waits for the others, then spins `hold` atomic reads."""
    for item in range(lanes * LANE_TASK):
        if item % LANE_TASK == 0:
            ti.atomic_add(count[None], 1)
            spins = 0
            while ti.atomic_add(count[None], 0) < lanes and spins < WAIT_SPINS:
                spins += 1
            for _ in range(hold):
                ti.atomic_add(count[None], 0)


def _cpu_ns():
    """CPU time (ns) of each thread of this process but the calling one: {thread id: ns}."""
    me = threading.get_native_id()
    out = {}
    for name in os.listdir("/proc/self/task"):
        if int(name) == me:
            continue
        try:
            with open(f"/proc/self/task/{name}/schedstat") as f:
                out[int(name)] = int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            pass  # a thread that ended meanwhile, or a kernel without schedstat
    return out


def find_workers(threads):
    """Thread ids of Taichi's `threads` CPU worker threads (Taichi running on the CPU), or None when PROBE_TRIES
    probes do not single out exactly that many."""
    count = ti.field(ti.i32, shape=())
    hold_lanes(count, threads, 0)  # compile (and wake the workers) before measuring
    for _ in range(PROBE_TRIES):
        count[None] = 0
        before = _cpu_ns()
        hold_lanes(count, threads, HOLD_SPINS)
        after = _cpu_ns()
        held = sorted(t for t in after if after[t] - before.get(t, after[t]) >= MIN_HELD_NS)
        if len(held) == threads:
            return held
    return None


def pin_workers(threads):
    """Pin Taichi's CPU worker threads one to each CPU this process may run on, if there are exactly `threads` of
    those CPUs (config.pins_workers, module docstring); returns {thread id: CPU} of what was pinned ({} when
    nothing was)."""
    if not pins_workers(threads):
        return {}
    cpus = sorted(os.sched_getaffinity(0))
    workers = find_workers(threads)
    if workers is None:
        return {}
    pinned = {}
    for tid, cpu in zip(workers, cpus):
        try:
            os.sched_setaffinity(tid, {cpu})
        except OSError:  # not allowed here (a sandbox): leave the placement to the scheduler
            for t in pinned:
                os.sched_setaffinity(t, set(cpus))
            return {}
        pinned[tid] = cpu
    return pinned
