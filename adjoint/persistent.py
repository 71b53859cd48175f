"""Reverse of mls_mpm.persistent: a reverse pass of the parallel schedule on a CPU in one launch, each lane's thread
running its share of adjoint.step's reverse loops step after step, with spin barriers between them.

Per reverse step f: reverse G2P of the lane's particles into its private dL/dv_i grid, a barrier, the reverse grid
operations of its share of the nodes (summing the private grids; v_i of step f - 1 recomputed into the one velocity
slot), a barrier, and reverse P2G of its particles, which read the dL/dm_i, dL/dp_i that barrier published; the next
reverse step's first barrier orders it before the grid loop that overwrites them. The same bodies over the same
shares in the same order as run_parallel_reverse: the adjoints equal its own bit for bit.
"""
import taichi as ti

from mls_mpm.grid import grid_op_node
from mls_mpm.persistent import barrier, chunk, chunks, lane_shares, node_of, tick
from mls_mpm.state import LANE_TASK

from .state import zero_particle
from .step import grid_node_reverse
from .transfer import check_particle_reverse, g2p_particle_reverse, p2g_particle_reverse


@ti.kernel
def run_persistent_reverse(s: ti.template(), a: ti.template(), f0: ti.i32, f1: ti.i32):
    """Reverse steps f1-1 down to f0 in one launch of s.lanes tasks (s.sync zero before it; twin of
    mls_mpm.persistent.run_persistent)."""
    for item in range(s.lanes * LANE_TASK):
        if item % LANE_TASK == 0:
            lane, lo, hi, k0, k1 = lane_shares(s, item)
            arrived = 0
            alive = True
            if ti.static(not s.every_velocity):  # v_i of the pass's last step into the one slot (velocity_loop)
                for c in range(chunks(k0, k1)):
                    c0, c1 = chunk(k0, k1, c)
                    for k in range(c0, c1):
                        grid_op_node(s, f1 - 1, node_of(s, k))
                    tick(s, lane)
                arrived += s.lanes
                alive = barrier(s, arrived)
            for j in range(f1 - f0):
                f = f1 - 1 - j
                if alive:
                    for c in range(chunks(lo, hi)):
                        c0, c1 = chunk(lo, hi, c)
                        for p in range(c0, c1):
                            g2p_particle_reverse(s, a, f, p, lane)
                        tick(s, lane)
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:
                    for c in range(chunks(k0, k1)):
                        c0, c1 = chunk(k0, k1, c)
                        for k in range(c0, c1):
                            grid_node_reverse(s, a, f, node_of(s, k), f0)
                        tick(s, lane)
                    arrived += s.lanes
                    alive = barrier(s, arrived)
                if alive:
                    for c in range(chunks(lo, hi)):
                        c0, c1 = chunk(lo, hi, c)
                        for p in range(c0, c1):
                            p2g_particle_reverse(s, a, f, p)
                            zero_particle(a, (f + 1) % 2, p)
                            check_particle_reverse(s, a, f, p)
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
