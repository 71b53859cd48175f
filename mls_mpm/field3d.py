"""The mass field of one 3D frame on the simulation grid, in numpy: what the 3D outputs (export3d, render3d) share.

`splat` is the P2G of eq 15 (node mass m_i = sum_p N(x_i - x_p) m_p) and eq 12 (colour-mass c_i = sum_p
N(x_i - x_p) m_p c_p) with the simulation's cubic B-spline (images.bspline, the numpy twin of kernels.weights);
`gather` the G2P of a node value back to points (eq 18's interpolation), `trilinear` the linear interpolation
of a node grid at points (the field marching cubes and the preview's ray marcher see between nodes).
Node i sits at x_i = i dx; nodes beyond the grid are dropped. Sums run with np.bincount in particle order, so a
frame's grids are reproducible to the bit.
"""
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .images import bspline

OFFSETS = np.arange(4)  # the 4 nodes of the stencil along an axis, from base = floor(x / dx) - 1


def _stencil(x, n_grid):
    """(flat node indices (P, 4^dim), weights N(x_i - x_p) (P, 4^dim), on-grid mask) of points x (P, dim)."""
    P, dim = x.shape
    base = np.floor(x * n_grid).astype(np.int64) - 1  # (P, dim)
    w = bspline(x[:, :, None] * n_grid - (base[:, :, None] + OFFSETS))  # (P, dim, 4)
    N = np.ones((P, 1))
    flat = np.zeros((P, 1), np.int64)
    ok = np.ones((P, 1), bool)
    for d in range(dim):  # first axis outermost, as the grid's C order
        i = base[:, d, None] + OFFSETS  # (P, 4)
        N = (N[:, :, None] * w[:, d, None, :]).reshape(P, -1)
        flat = (flat[:, :, None] * n_grid + i[:, None, :]).reshape(P, -1)
        ok = (ok[:, :, None] & ((i >= 0) & (i < n_grid))[:, None, :]).reshape(P, -1)
    return flat, N, ok


def splat(x, m_p, n_grid, colors=None):
    """(m, c): node masses (n,)*dim (eq 15) and colour-masses (n,)*dim + (3,) (eq 12; None without colors).

    x: (P, dim) positions in the unit domain; m_p: a number or (P,); colors: (P, 3) floats."""
    x = np.asarray(x, np.float64)
    P, dim = x.shape
    m = np.broadcast_to(np.asarray(m_p, np.float64), (P,))
    flat, N, ok = _stencil(x, n_grid)
    size = n_grid ** dim
    idx, Nm = flat[ok], (N * m[:, None])[ok]
    grid_m = np.bincount(idx, Nm, minlength=size).reshape((n_grid,) * dim)
    if colors is None:
        return grid_m, None
    rows = np.broadcast_to(np.arange(P)[:, None], ok.shape)[ok]
    colors = np.asarray(colors, np.float64)
    grid_c = np.stack([np.bincount(idx, Nm * colors[rows, k], minlength=size) for k in range(3)], axis=-1)
    return grid_m, grid_c.reshape((n_grid,) * dim + (3,))


def gather(grid, x):
    """sum_i N(x_i - x_p) g_i at points x (P, dim): the B-spline interpolation (G2P) of a node grid."""
    grid = np.asarray(grid, np.float64)
    x = np.asarray(x, np.float64)
    flat, N, ok = _stencil(x, grid.shape[0])
    return np.sum(np.where(ok, N * grid.ravel()[np.where(ok, flat, 0)], 0.0), axis=1)


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
    m, c = splat(x, m_p, n_grid, colors)
    return MassField(m, c, float(density))
