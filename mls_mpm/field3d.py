"""The mass field of one 3D frame on the simulation grid, in numpy: what the 3D outputs (export3d, render3d) share.

`splat` is the P2G of eq 15 (node mass m_i = sum_p N(x_i - x_p) m_p) and eq 12 (colour-mass c_i = sum_p
N(x_i - x_p) m_p c_p) with the simulation's cubic B-spline (`_axis_weights`, the numpy twin of kernels.weights);
`gather` the G2P of a node value back to points (eq 18's interpolation), `trilinear` the linear interpolation
of a node grid at points (the field marching cubes and the preview's ray marcher see between nodes).
Node i sits at x_i = i dx; nodes beyond the grid are dropped. Both are products with one sparse matrix of the
particles' weights (`stencil_matrix`), whose sums run in particle order, so a frame's grids are reproducible to
the bit.
"""
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse


OFFSETS = np.arange(4)  # the 4 nodes of the stencil along an axis, from base = floor(x / dx) - 1


def _axis_weights(x, n_grid):
    """(node indices (P, dim, 4), weights N1 (P, dim, 4)) of the stencil of points x (P, dim) along each axis:
    kernels.weights in numpy. Nodes off the grid get weight 0 and an index clamped onto it, so that sums over
    the stencil drop them without a mask (as sampling.axis_stencil). Cubes as products: numpy's ** 3 calls
    pow, which took 6 of a 32^3 frame's 27 ms."""
    base = np.floor(x * n_grid).astype(np.int64) - 1
    fx = x * n_grid - base  # in [1, 2): each of the 4 nodes in a fixed piece of N1
    a, b = 2.0 - fx, fx - 1.0  # the distances to nodes 2 and 1, both in (0, 1]
    w = np.stack([a * a * a / 6.0, b * b * (0.5 * b - 1.0) + 2.0 / 3.0, a * a * (0.5 * a - 1.0) + 2.0 / 3.0,
                  b * b * b / 6.0], axis=-1)
    i = base[:, :, None] + OFFSETS
    on = (i >= 0) & (i < n_grid)
    return np.clip(i, 0, n_grid - 1), np.where(on, w, 0.0)


def stencil_matrix(x, n_grid):
    """A sparse (P, n_grid^dim) with A[p, i] = N(x_i - x_p) for points x (P, dim), nodes flat in the grid's C
    order (first axis outermost); nodes off the grid have weight 0. P2G is A^T @ (per-particle values), G2P
    A @ (node values): scipy's sparse products run in particle order, so a frame's grids are reproducible to
    the bit (one product for mass and colour: half the time of a np.bincount per channel)."""
    i, w = _axis_weights(np.asarray(x, np.float64), n_grid)
    P, dim = x.shape
    i = i.astype(np.int32)  # scipy's index type (n_grid^3 < 2^31 for any grid that fits in memory)
    flat, N = i[:, 0], w[:, 0]
    for d in range(1, dim):
        flat = (flat[:, :, None] * n_grid + i[:, d, None, :]).reshape(P, -1)
        N = (N[:, :, None] * w[:, d, None, :]).reshape(P, -1)
    k = flat.shape[1]
    return sparse.csr_matrix((N.ravel(), flat.ravel(), np.arange(0, P * k + 1, k, dtype=np.int32)),
                             shape=(P, n_grid ** dim))


def splat(x, m_p, n_grid, colors=None, stencil=None):
    """(m, c): node masses (n,)*dim (eq 15) and colour-masses (n,)*dim + (3,) (eq 12; None without colors).

    x: (P, dim) positions in the unit domain; m_p: a number or (P,); colors: (P, 3) floats; stencil: x's
    `stencil_matrix`, when the caller has it."""
    x = np.asarray(x, np.float64)
    P, dim = x.shape
    A = stencil_matrix(x, n_grid) if stencil is None else stencil
    m = np.broadcast_to(np.asarray(m_p, np.float64), (P,))
    values = m[:, None] if colors is None else np.concatenate([m[:, None], m[:, None] * colors], axis=1)
    grids = A.T @ values  # (n^dim, 1 or 4)
    grid_m = grids[:, 0].reshape((n_grid,) * dim)
    if colors is None:
        return grid_m, None
    return grid_m, grids[:, 1:].reshape((n_grid,) * dim + (3,))


def gather(grid, x, stencil=None):
    """sum_i N(x_i - x_p) g_i at points x (P, dim): the B-spline interpolation (G2P) of a node grid."""
    grid = np.asarray(grid, np.float64)
    A = stencil_matrix(np.asarray(x, np.float64), grid.shape[0]) if stencil is None else stencil
    return A @ grid.ravel()


def trilinear(grid, points, n_grid):
    """Linear interpolation of a node grid (n,)*dim (or with a trailing channel axis) at domain points (P, dim);
    0 beyond the grid."""
    coords = np.asarray(points, np.float64).T * n_grid  # node index coordinates, (dim, P)
    grid = np.asarray(grid, np.float64)
    dim = coords.shape[0]
    if grid.ndim == dim:
        return ndimage.map_coordinates(grid, coords, order=1, mode="constant", cval=0.0)
    return np.stack([ndimage.map_coordinates(grid[..., k], coords, order=1, mode="constant", cval=0.0)
                     for k in range(grid.shape[-1])], axis=-1)


@dataclass(frozen=True)
class MassField:
    """One frame's grids. m: node masses (n, n, n); c: colour-masses (n, n, n, 3) or None; density: the rest
    density, which sets `rest`, the mass of a node inside material at rest density (density * dx^3)."""

    m: np.ndarray
    c: np.ndarray | None
    density: float

    @property
    def n_grid(self):
        return self.m.shape[0]

    @property
    def rest(self):
        """density * dx^3: the B-spline weights of a node sum to dx^3 over a uniform body (t = m / rest = 1)."""
        return self.density / self.n_grid ** 3

    @property
    def t(self):
        """The normalised node masses m_i / rest (thesis 7.1's colormap input)."""
        return self.m / self.rest

    def colors_at(self, points):
        """RGB floats (P, 3) of the colour field c(x) / m(x) at points (P, 3), linear between nodes (m > 0 at
        the points asked: the mesh's vertices lie on an iso level of m)."""
        m = trilinear(self.m, points, self.n_grid)
        c = trilinear(self.c, points, self.n_grid)
        return np.clip(c / np.maximum(m, 1e-300)[:, None], 0.0, 1.0)  # m = 0 only off the body, where c = 0

    def density_at(self, x):
        """Density at points x (P, 3): the node masses gathered back (G2P) over the cell volume dx^3; the rest
        density deep inside a body at rest, about half of it at a flat free surface."""
        return gather(self.m, x) * self.n_grid ** 3


def mass_field(x, m_p, n_grid, density, colors=None):
    """The MassField of particles x (P, 3) of mass m_p (and colours (P, 3)) on an n_grid^3 grid."""
    return MassField(*splat(x, m_p, n_grid, colors), float(density))


def frame_field(x, m_p, n_grid, density, colors=None):
    """(`mass_field`, the density at the particles: `MassField.density_at` x), the splat and the gather
    sharing the particles' stencil (what one 3D frame's outputs need)."""
    x = np.asarray(x, np.float64)
    stencil = stencil_matrix(x, n_grid)
    m, c = splat(x, m_p, n_grid, colors, stencil)
    return MassField(m, c, float(density)), gather(m, x, stencil) * n_grid ** 3
