"""Images as shapes (thesis 5.5): load an image, sample particles on its material pixels, splat them on a grid.

The domain is the unit square with y pointing up; an image's row 0 is its top.
A pixel is material where its alpha is > 0.5 and it is not white (some RGB channel <= 0.9).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from .errors import UserError

WHITE = 0.9  # a pixel whose R, G and B all exceed this is background
OPAQUE = 0.5  # a pixel whose alpha is at most this is background
JITTER = 0.5  # lattice jitter, as a fraction of the sub-cell spacing


class ImageError(UserError):
    """An image is missing, unreadable or holds no material; the message is one line naming the file."""


def load_image(path) -> np.ndarray:
    """Read an image (palette, grayscale, 16-bit, RGB, RGBA, ...) as (H, W, 4) float RGBA in [0, 1]."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such image file")
    try:
        with Image.open(path) as img:
            img.seek(0)  # first frame of an animation
            img.load()
            return _rgba(img)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        raise ImageError(f"{path}: not an image Pillow can read ({reason})") from None


def _rgba(img: Image.Image) -> np.ndarray:
    """Pillow image of any mode -> (H, W, 4) float RGBA in [0, 1]; 16- and 32-bit gray keep their precision."""
    if img.mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        gray = np.asarray(img, dtype=np.float64)
        top = 65535.0 if img.mode != "I" or gray.max(initial=0) > 255 else 255.0
        gray = np.clip(gray / top, 0.0, 1.0)
        return np.dstack([gray, gray, gray, np.ones_like(gray)])
    if img.mode == "F":
        gray = np.clip(np.asarray(img, dtype=np.float64), 0.0, 1.0)
        return np.dstack([gray, gray, gray, np.ones_like(gray)])
    return np.asarray(img.convert("RGBA"), dtype=np.float64) / 255.0


def material(rgba: np.ndarray) -> np.ndarray:
    """(H, W) bool: alpha > 0.5 and not white (not all of R, G, B > 0.9)."""
    return (rgba[..., 3] > OPAQUE) & ~np.all(rgba[..., :3] > WHITE, axis=-1)


def default_region(n_grid: int, bound: int = 3) -> tuple:
    """The centred square [(bound + 2) dx, 1 - (bound + 2) dx]^2 that keeps a margin beyond the walls."""
    m = (bound + 2) / n_grid
    return (m, m, 1.0 - m, 1.0 - m)


def fit(shape, region) -> tuple:
    """(ox, oy, s): the image of shape (H, W, ...) scaled by s (domain units per pixel), aspect kept,
    centred in region (x0, y0, x1, y1); pixel (row r, col c) covers x in ox + [c, c+1] s, y in oy + [H-1-r, H-r] s."""
    H, W = shape[:2]
    x0, y0, x1, y1 = region
    s = min((x1 - x0) / W, (y1 - y0) / H)
    return x0 + 0.5 * ((x1 - x0) - W * s), y0 + 0.5 * ((y1 - y0) - H * s), s


def pixel_of(x: np.ndarray, shape, region):
    """(row, col, inside) of the pixel under each domain point x (N, 2) for an image fitted into region."""
    H, W = shape[:2]
    ox, oy, s = fit(shape, region)
    col = np.floor((x[:, 0] - ox) / s).astype(np.int64)
    row = H - 1 - np.floor((x[:, 1] - oy) / s).astype(np.int64)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    return np.clip(row, 0, H - 1), np.clip(col, 0, W - 1), inside


def sample_particles(rgba, n_grid, particles_per_cell, region=None, seed=0, bound=3):
    """Particles on the material pixels of rgba fitted into region: (x (N, 2), colors (N, 3)).

    particles_per_cell per simulation cell: a jittered sqrt(ppc) x sqrt(ppc) lattice when ppc is a square,
    else uniform random points; deterministic for a seed. region defaults to default_region(n_grid, bound).
    """
    rgba = np.asarray(rgba, dtype=np.float64)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or min(rgba.shape[:2]) < 1:
        raise ImageError(f"image: expected an (H, W, 4) RGBA array, got shape {rgba.shape}")
    mask = material(rgba)
    if not mask.any():
        raise ImageError("image has no material pixels (opaque and not white)")
    region = default_region(n_grid, bound) if region is None else tuple(float(r) for r in region)
    H, W = rgba.shape[:2]
    ox, oy, s = fit(rgba.shape, region)
    dx = 1.0 / n_grid
    i0, i1 = math.floor(ox / dx), math.ceil((ox + W * s) / dx)  # cells touching the fitted image
    j0, j1 = math.floor(oy / dx), math.ceil((oy + H * s) / dx)
    cells = np.stack(np.meshgrid(np.arange(i0, i1), np.arange(j0, j1), indexing="ij"), -1).reshape(-1, 1, 2)
    rng = np.random.default_rng(seed)
    k = math.isqrt(particles_per_cell)
    if k * k == particles_per_cell:  # jittered lattice: sub-cell centres moved by up to JITTER/2 sub-cells
        a = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(1, -1, 2)
        u = 0.5 + JITTER * (rng.random((len(cells), k * k, 2)) - 0.5)
        offsets = (a + u) / k
    else:
        offsets = rng.random((len(cells), particles_per_cell, 2))
    x = ((cells + offsets) * dx).reshape(-1, 2)
    row, col, inside = pixel_of(x, rgba.shape, region)
    keep = inside & mask[row, col]
    if not keep.any():
        raise ImageError(f"image: no particle landed on a material pixel; the shape is smaller than the "
                         f"particle spacing ({dx / max(k, 1):.3g}) at n_grid {n_grid}")
    return x[keep], rgba[row[keep], col[keep], :3].copy()


def bspline(t: np.ndarray) -> np.ndarray:
    """Cubic B-spline N1(t): |t|^3/2 - t^2 + 2/3 for |t| < 1, (2 - |t|)^3/6 for 1 <= |t| < 2, else 0."""
    a = np.abs(t)
    return np.where(a < 1.0, 0.5 * a ** 3 - a ** 2 + 2.0 / 3.0, np.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0))


def splat_grid(x, mass, res, values=None) -> np.ndarray:
    """P2G with the cubic B-spline onto a res x res grid: (res, res) mass, or (res, res, C) of mass * values.

    mass: a number or one per particle; entry [i, j] is the node at (i / res, j / res); nodes outside are dropped.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1, 2)
    mass = np.broadcast_to(np.asarray(mass, dtype=np.float64), (len(x),))
    carried = mass[:, None] if values is None else mass[:, None] * np.asarray(values, np.float64).reshape(len(x), -1)
    base = np.floor(x * res).astype(np.int64) - 1  # (N, 2)
    fx = x * res - base  # in [1, 2)
    offsets = np.arange(4)
    w = bspline(fx[:, :, None] - offsets)  # (N, 2, 4): weight of node base + j per axis
    I = base[:, 0, None, None] + offsets[None, :, None]  # (N, 4, 1)
    J = base[:, 1, None, None] + offsets[None, None, :]  # (N, 1, 4)
    N = w[:, 0, :, None] * w[:, 1, None, :]  # (N, 4, 4)
    I, J = np.broadcast_arrays(I, J)
    ok = (I >= 0) & (I < res) & (J >= 0) & (J < res)
    grid = np.zeros((res * res, carried.shape[1]))
    p = np.broadcast_to(np.arange(len(x))[:, None, None], ok.shape)[ok]
    np.add.at(grid, I[ok] * res + J[ok], N[ok][:, None] * carried[p])
    grid = grid.reshape(res, res, -1)
    return grid[..., 0] if values is None else grid
