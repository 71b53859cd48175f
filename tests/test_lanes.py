"""The lane loops of the parallel CPU schedule (mls_mpm.state.LANE_TASK, lane_span): each lane's particles run on
one thread, in index order, and the lanes run on different threads at once.

P2G and reverse G2P scatter into one private grid per lane with plain adds, so two threads in one lane would race;
and a loop over the lanes themselves ran as one task of Taichi's, on one thread (the lanes one after the other).
The loop below has the shape of step.step_loops' and adjoint.step.step_loops_reverse's scatter loops and records
which thread ran each item (ti.global_thread_idx(), the CPU thread's index).
"""
import pytest
import taichi as ti

import mls_mpm
from conftest import scene_config
from mls_mpm import runtime
from mls_mpm.state import LANE_TASK, State, lane_span

N = 3001  # not a multiple of the lanes or of LANE_TASK: the last lane and the last items run short
LANES = 2


@ti.kernel
def record(s: ti.template(), visits: ti.template(), thread: ti.template(), busy_out: ti.template(), spin: ti.i32):
    for item in range(s.lanes * LANE_TASK):
        lane, lo, hi = lane_span(s, item)
        busy = 0
        for k in range(spin):  # work enough that the second thread wakes and takes a task
            busy = (busy * 31 + k) % 1000003
        thread[item] = ti.global_thread_idx()
        busy_out[item] = busy  # kept, so that the work is not optimized away
        for p in range(lo, hi):
            visits[p, lane] += 1


@pytest.fixture(scope="module")
def lanes():
    cfg = scene_config(threads=LANES, steps=2, stride=1)
    runtime.ensure(cfg, tape=False)
    s = State(cfg, N, lanes=LANES)
    visits = ti.field(ti.i32, shape=(N, LANES))
    thread = ti.field(ti.i32, shape=LANES * LANE_TASK)
    yield s, visits, thread, ti.field(ti.i32, shape=LANES * LANE_TASK)
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"), tape=False)


def run(lanes, spin):
    s, visits, thread, busy = lanes
    visits.fill(0)
    record(s, visits, thread, busy, spin)
    return visits.to_numpy(), thread.to_numpy().reshape(LANES, LANE_TASK)


def test_each_particle_once_in_its_lane(lanes):
    """Every particle is visited once, by the lane of its index range (lane 0: the first ceil(N / 2))."""
    visits, _ = run(lanes, 0)
    assert visits.sum(axis=1).tolist() == [1] * N
    first = -(-N // LANES)
    assert visits[:first, 0].all() and visits[first:, 1].all()


def test_one_thread_per_lane_and_lanes_in_parallel(lanes):
    """Within a lane every item ran on one thread (no race on its private grid); the two lanes ran on two threads.
    The second is a matter of timing (a thread that wakes late leaves both tasks to the other), so it may take a
    few tries with more work per item; the first must hold in every try."""
    together = False
    for spin in (2000, 20000, 200000, 2000000):
        _, thread = run(lanes, spin)
        for lane in range(LANES):
            assert len(set(thread[lane].tolist())) == 1, f"lane {lane} ran on threads {sorted(set(thread[lane]))}"
        if thread[0, 0] != thread[1, 0]:
            together = True
            break
    assert together, "both lanes ran on one thread in every try"
