"""Images as shapes (thesis 5.5): load an image, sample particles on its material pixels, splat them on a grid.

The domain is the unit square with y pointing up; an image's row 0 is its top.
A pixel is material where its alpha is > 0.5 and it is not white (some RGB channel <= 0.9).
An image has at most MAX_PIXELS pixels, checked in its header before any pixel is decoded.
"""
from __future__ import annotations

import math
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError
from .errors import UserError

WHITE = 0.9  # a pixel whose R, G and B all exceed this is background
OPAQUE = 0.5  # a pixel whose alpha is at most this is background
JITTER = 0.5  # lattice jitter, as a fraction of the sub-cell spacing
MAX_PIXELS = 50_000_000  # width x height of the largest image accepted (50 megapixels, 1.6 GB as float RGBA)
RGBA_BYTES = 4 * 8  # bytes per pixel of the float64 RGBA array load_image returns
DECODE_BYTES = RGBA_BYTES + 4 + 8  # bytes per pixel while loading: the RGBA array, Pillow's 8-bit copy, temporaries
STENCIL = 4  # nodes of a particle's B-spline stencil per axis
ROUND_OFF = 1e-9  # cells: particle_bound takes a box edge this close to a cell edge as on it
CHUNK = 1 << 16  # cells (sample_particles) or particles (splat_grid) processed at a time, to bound temporaries


class ImageError(UserError):
    """An image is missing, unreadable or holds no material; the message is one line naming the file."""


@contextmanager
def _opened(path):
    """The Pillow image at path, its header read and its size checked against MAX_PIXELS, not yet decoded.

    Pillow's own decompression-bomb limit is lifted meanwhile: the stricter MAX_PIXELS replaces it, and a
    refusal must name the image's size, which Pillow's error does not give.
    """
    path = Path(path)
    if not path.is_file():
        if not path.exists():
            raise ImageError(f"{path}: no such image file")
        what = "is a directory" if path.is_dir() else "is not a regular file (a device, pipe or socket)"
        raise ImageError(f"{path}: {what}; expected an image file")
    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        with Image.open(path) as img:
            img.seek(0)  # first frame of an animation
            width, height = img.size
            if width * height > MAX_PIXELS:
                raise ImageError(f"{path}: the image is {width} x {height} = {width * height / 1e6:.4g} megapixels, "
                                 f"above the limit of {MAX_PIXELS / 1e6:g} megapixels (images.MAX_PIXELS); "
                                 "expected a smaller image")
            yield img
    except ImageError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        raise ImageError(f"{path}: not an image Pillow can read ({reason})") from None
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def image_size(path) -> tuple:
    """(width, height) from an image's header, without decoding its pixels."""
    with _opened(path) as img:
        return img.size


def check_image(path) -> tuple:
    """(width, height) of a readable image of at most MAX_PIXELS pixels, its pixels decoded but not converted."""
    with _opened(path) as img:
        img.load()
        return img.size


def load_image(path) -> np.ndarray:
    """Read an image (palette, grayscale, 16-bit, RGB, RGBA, ...) as (H, W, 4) float RGBA in [0, 1]."""
    with _opened(path) as img:
        img.load()
        return _rgba(img)


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


def default_region(n_grid: int, bound: int = 3, dim: int = 2) -> tuple:
    """The centred square (cube for dim = 3) [(bound + 2) dx, 1 - (bound + 2) dx]^dim that keeps a margin beyond
    the walls: (x0, y0, x1, y1), or (x0, y0, z0, x1, y1, z1)."""
    m = (bound + 2) / n_grid
    return (m,) * dim + (1.0 - m,) * dim


def fit_box(lo, hi, region) -> tuple:
    """(origin, s): the box [lo, hi] (dim numbers each) scaled by s, aspect kept, centred in region (x0, y0(, z0),
    x1, y1(, z1)); its point p lands at origin + s (p - lo). Axes where the box is flat do not limit s."""
    dim = len(lo)
    size = [float(h) - float(l) for l, h in zip(lo, hi)]
    room = [float(region[dim + a]) - float(region[a]) for a in range(dim)]
    s = min(r / e for r, e in zip(room, size) if e > 0)
    return tuple(float(region[a]) + 0.5 * (room[a] - size[a] * s) for a in range(dim)), s


def box_cells(origin, extent, dx) -> tuple:
    """(lo, hi): the cells [lo, hi) per axis touching the box origin + [0, extent] (dim numbers each)."""
    return (tuple(math.floor(o / dx) for o in origin),
            tuple(math.ceil((o + e) / dx) for o, e in zip(origin, extent)))


def fit(shape, region) -> tuple:
    """(ox, oy, s): the image of shape (H, W, ...) scaled by s (domain units per pixel), aspect kept,
    centred in region (x0, y0, x1, y1); pixel (row r, col c) covers x in ox + [c, c+1] s, y in oy + [H-1-r, H-r] s."""
    H, W = shape[:2]
    (ox, oy), s = fit_box((0, 0), (W, H), region)
    return ox, oy, s


def pixel_of(x: np.ndarray, shape, region):
    """(row, col, inside) of the pixel under each domain point x (N, 2) for an image fitted into region."""
    H, W = shape[:2]
    ox, oy, s = fit(shape, region)
    col = np.floor((x[:, 0] - ox) / s).astype(np.int64)
    row = H - 1 - np.floor((x[:, 1] - oy) / s).astype(np.int64)
    inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    return np.clip(row, 0, H - 1), np.clip(col, 0, W - 1), inside


def cell_range(shape, n_grid, region) -> tuple:
    """(i0, i1, j0, j1): the simulation cells [i0, i1) x [j0, j1) touching an image of shape (H, W, ...) fitted
    into region; sample_particles draws particles_per_cell points in each."""
    H, W = shape[:2]
    ox, oy, s = fit(shape, region)
    (i0, j0), (i1, j1) = box_cells((ox, oy), (W * s, H * s), 1.0 / n_grid)
    return i0, i1, j0, j1


def particle_bound(mask, n_grid, particles_per_cell, region=None, bound=3) -> int:
    """An upper bound of the particles sample_particles keeps on the material mask (H, W), without sampling:
    particles_per_cell times the cells whose interior meets the material pixels' bounding box, or meets each
    material pixel (at most ceil(s / dx) + 1 cells per axis), whichever is fewer. A box edge within ROUND_OFF
    of a cell edge is taken as on it (only a particle rounded onto that edge could then be missed)."""
    mask = np.asarray(mask, bool)
    region = default_region(n_grid, bound) if region is None else tuple(float(r) for r in region)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return 0
    H, W = mask.shape
    ox, oy, s = fit(mask.shape, region)
    dx = 1.0 / n_grid
    i0, i1, j0, j1 = cell_range(mask.shape, n_grid, region)
    i_lo = max(i0, math.floor((ox + cols[0] * s) / dx + ROUND_OFF))
    i_hi = min(i1, math.ceil((ox + (cols[-1] + 1) * s) / dx - ROUND_OFF))
    j_lo = max(j0, math.floor((oy + (H - 1 - rows[-1]) * s) / dx + ROUND_OFF))
    j_hi = min(j1, math.ceil((oy + (H - rows[0]) * s) / dx - ROUND_OFF))
    per_pixel = (math.ceil(s / dx) + 1) ** 2
    return particles_per_cell * min((i_hi - i_lo) * (j_hi - j_lo), int(np.count_nonzero(mask)) * per_pixel)


def sample_particles(rgba, n_grid, particles_per_cell, region=None, seed=0, bound=3):
    """Particles on the material pixels of rgba fitted into region: (x (N, 2), colors (N, 3)).

    particles_per_cell per simulation cell: a jittered sqrt(ppc) x sqrt(ppc) lattice when ppc is a square,
    else uniform random points; deterministic for a seed. region defaults to default_region(n_grid, bound).
    The cells are drawn in chunks (about CHUNK points at a time), so temporaries stay small.
    """
    rgba = np.asarray(rgba, dtype=np.float64)
    if rgba.ndim != 3 or rgba.shape[2] != 4 or min(rgba.shape[:2]) < 1:
        raise ImageError(f"image: expected an (H, W, 4) RGBA array, got shape {rgba.shape}")
    mask = material(rgba)
    if not mask.any():
        raise ImageError("image has no material pixels (opaque and not white)")
    region = default_region(n_grid, bound) if region is None else tuple(float(r) for r in region)
    dx = 1.0 / n_grid
    i0, i1, j0, j1 = cell_range(rgba.shape, n_grid, region)
    rng = np.random.default_rng(seed)
    k = math.isqrt(particles_per_cell)
    xs, colors = [], []
    for x in cell_samples((i0, j0), (i1, j1), particles_per_cell, dx, rng):
        row, col, inside = pixel_of(x, rgba.shape, region)
        keep = inside & mask[row, col]
        xs.append(x[keep])
        colors.append(rgba[row[keep], col[keep], :3])
    x = np.concatenate(xs)
    if not len(x):
        raise ImageError(f"image: no particle landed on a material pixel; the shape is smaller than the "
                         f"particle spacing ({dx / max(k, 1):.3g}) at n_grid {n_grid}")
    return x, np.concatenate(colors)


def lattice_side(particles_per_cell, dim=2) -> int:
    """k when particles_per_cell = k^dim (a jittered k^dim lattice per cell), else 0 (uniform random points)."""
    k = round(particles_per_cell ** (1.0 / dim))
    return k if k ** dim == particles_per_cell else 0


def cell_samples(lo, hi, particles_per_cell, dx, rng):
    """particles_per_cell points in each simulation cell of the box [lo, hi) (cell indices per axis), yielded
    as (n, dim) arrays of about CHUNK points, cells in C (i-major) order.

    A jittered k^dim lattice when particles_per_cell = k^dim (sub-cell centres moved by up to JITTER/2
    sub-cells), else uniform random points; the random stream does not depend on the chunk size.
    """
    lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
    dim, counts = len(lo), tuple(int(c) for c in hi - lo)
    n_cells = math.prod(counts)
    k = lattice_side(particles_per_cell, dim)
    a = np.stack(np.meshgrid(*[np.arange(k)] * dim, indexing="ij"), -1).reshape(1, -1, dim)
    step = max(1, CHUNK // particles_per_cell)
    for start in range(0, n_cells, step):
        index = np.arange(start, min(start + step, n_cells))
        cells = (np.stack(np.unravel_index(index, counts), -1) + lo)[:, None, :]
        if k:
            u = 0.5 + JITTER * (rng.random((len(index), k ** dim, dim)) - 0.5)
            offsets = (a + u) / k
        else:
            offsets = rng.random((len(index), particles_per_cell, dim))
        yield ((cells + offsets) * dx).reshape(-1, dim)


def bspline(t: np.ndarray) -> np.ndarray:
    """Cubic B-spline N1(t): |t|^3/2 - t^2 + 2/3 for |t| < 1, (2 - |t|)^3/6 for 1 <= |t| < 2, else 0."""
    a = np.abs(t)
    return np.where(a < 1.0, 0.5 * a ** 3 - a ** 2 + 2.0 / 3.0, np.where(a < 2.0, (2.0 - a) ** 3 / 6.0, 0.0))


def splat_grid(x, mass, res, values=None) -> np.ndarray:
    """P2G with the cubic B-spline onto a res^dim grid (dim = x.shape[-1], 2 or 3): (res,) * dim mass, or
    (res,) * dim + (C,) of mass * values.

    mass: a number or one per particle; entry [i, j(, k)] is the node at (i, j(, k)) / res; nodes outside are
    dropped. Particles are splatted in chunks, in order, so the sums do not depend on the chunk size.
    """
    x = np.asarray(x, dtype=np.float64)
    dim = x.shape[-1] if x.ndim > 1 else 2
    x = x.reshape(-1, dim)
    mass = np.broadcast_to(np.asarray(mass, dtype=np.float64), (len(x),))
    values = None if values is None else np.asarray(values, np.float64).reshape(len(x), -1)
    grid = np.zeros((res ** dim, 1 if values is None else values.shape[1]))
    step = max(1, CHUNK // STENCIL ** dim)
    for start in range(0, len(x), step):
        part = slice(start, start + step)
        _splat_into(grid, res, x[part], mass[part], None if values is None else values[part])
    grid = grid.reshape((res,) * dim + (-1,))
    return grid[..., 0] if values is None else grid


def _splat_into(grid, res, x, mass, values):
    """Add the particles x (n, dim) of mass (n,) carrying values (n, C) or None to grid (res^dim, C)."""
    n, dim = x.shape
    carried = mass[:, None] if values is None else mass[:, None] * values
    base = np.floor(x * res).astype(np.int64) - 1  # (n, dim)
    fx = x * res - base  # in [1, 2)
    offsets = np.arange(STENCIL)
    w = bspline(fx[:, :, None] - offsets)  # (n, dim, 4): weight of node base + j per axis

    def along(a, v):  # v (n, 4) laid along axis a of an (n, 4, ..., 4) stencil
        return v.reshape((n,) + (1,) * a + (STENCIL,) + (1,) * (dim - 1 - a))

    N, flat, ok = along(0, w[:, 0]), 0, True
    for a in range(dim):
        I = along(a, base[:, a, None] + offsets)
        if a:
            N = N * along(a, w[:, a])
        flat, ok = flat * res + I, ok & (I >= 0) & (I < res)
    N, flat, ok = np.broadcast_arrays(N, flat, ok)
    p = np.broadcast_to(np.arange(n).reshape((n,) + (1,) * dim), ok.shape)[ok]
    np.add.at(grid, flat[ok], N[ok][:, None] * carried[p])
