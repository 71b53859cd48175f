"""Reverse of one fused step (twin of mls_mpm.step.substep): the forward's loops in reverse order."""
import taichi as ti

from .grid import grid_op_reverse_node
from .state import zero_particle
from .transfer import g2p_reverse_particle, p2g_reverse_particle


@ti.kernel
def substep_reverse(s: ti.template(), a: ti.template(), f: ti.i32):
    """Zero step f's adjoints, then reverse G2P, reverse grid operations, reverse P2G."""
    for p in range(s.n_particles):
        zero_particle(a, f % 2, p)
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        a.adj_grid_v[i, j] = ti.Vector.zero(float, 2)
    for p in range(s.n_particles):
        g2p_reverse_particle(s, a, f, p)
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_reverse_node(s, a, f, i, j)
    for p in range(s.n_particles):
        p2g_reverse_particle(s, a, f, p)
