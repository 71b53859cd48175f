"""Reverse of mls_mpm.persistent: a reverse pass of the parallel schedule on a CPU in one launch, each lane's thread
running its share of adjoint.step's reverse loops step after step, with spin barriers between them.

Per reverse step f, from the pass's start f1 (adjoint.step: there only v_i of step f1 - 1 and the reverse G2P of step
f1 - 1) down to f0: the reverse grid operations of the lane's share of the nodes (summing the private dL/dv_i grids;
v_i of step f - 1 recomputed into the one velocity slot), a barrier, and its particles' fused reverse P2G of step f
and reverse G2P of step f - 1 (adjoint.step.particle_adjoint), which read the dL/dm_i, dL/dp_i that barrier
published and scatter into the lane's private grid; a barrier then orders them before the next step's grid loop,
which overwrites the one and sums the other. Two barriers a step, where separate reverse G2P and P2G loops needed
three. The same bodies over the same shares in the same order as run_parallel_reverse: the adjoints equal its own
bit for bit.
"""
import taichi as ti

from mls_mpm.active import node_in, reverse_box, volume
from mls_mpm.persistent import barrier, chunk, chunks, lane_shares, own_nodes, tick
from mls_mpm.state import LANE_TASK

from .step import grid_node_reverse, particle_adjoint


@ti.kernel
def run_persistent_reverse(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 after the pass's start (f = f1), in one launch of s.lanes tasks (s.sync zero
    before it; twin of mls_mpm.persistent.run_persistent)."""
    for item in range(s.lanes * LANE_TASK):
        if item % LANE_TASK == 0:
            lane, lo, hi = lane_shares(s, item)
            arrived = 0
            alive = True
            for j in range(f1 - f0 + 1):
                f = f1 - j
                if alive and j > 0:
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:  # the active boxes of steps f and f - 1 (mls_mpm.active), as the forward stored them
                    b0, b1 = reverse_box(s, f, f0, f1)
                    k0, k1 = own_nodes(s, lane, volume(b0, b1))
                    for c in range(chunks(k0, k1)):
                        c0, c1 = chunk(k0, k1, c)
                        for k in range(c0, c1):
                            grid_node_reverse(s, a, f, node_in(b0, b1, k), f0, f1)
                        tick(s, lane)
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:
                    for c in range(chunks(lo, hi)):
                        c0, c1 = chunk(lo, hi, c)
                        for p in range(c0, c1):
                            particle_adjoint(s, a, f, p, lane, f0, f1)
                        tick(s, lane)


def persistent_pass_reverse(s, a, f0, f1):
    """Reverse steps f1-1..f0 of a state with lanes by run_persistent_reverse; whether it finished the pass. If a barrier
    gave up, the private dL/dv_i grids are left zero, and the caller begins the whole reverse pass again (the adjoints
    re-seeded from the loss) with run_parallel_reverse (Simulator._pass)."""
    s.sync.fill(0)
    run_persistent_reverse(s, a, f0, f1)
    if s.sync[1] == 0:
        return True
    a.lane_adj_v.fill(0.0)
    return False
