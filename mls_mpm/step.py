"""One forward step f -> f + 1 fused into a single kernel launch (launch cost dominates small scenes)."""
import taichi as ti

from .grid import grid_op_node
from .transfer import check_particle, g2p_particle, p2g_particle


@ti.kernel
def substep(s: ti.template(), f: ti.i32):
    """Check step f, clear grid f, then P2G (eq 14-16), grid operations (eq 17 + gravity + walls), G2P (eq 18-21)."""
    for p in range(s.n_particles):
        check_particle(s, f, p)
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        s.grid_m[f, i, j] = 0.0
        s.grid_p[f, i, j] = ti.Vector.zero(float, 2)
    for p in range(s.n_particles):
        p2g_particle(s, f, p)
    for i, j in ti.ndrange(s.n_grid, s.n_grid):
        grid_op_node(s, f, i, j)
    for p in range(s.n_particles):
        g2p_particle(s, f, p)
