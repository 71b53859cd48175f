"""3D shapes as particles (sim.dim = 3): built-in solids, triangle meshes and extruded 2D images.

A shape is a `Solid`: a box `[lo, hi]` in its own units (its frame) and an inside test. The frame is fitted
into scene.region like an image (aspect kept, centred; images.fit_box), and particles_per_cell points are drawn
in every simulation cell it touches (images.cell_samples: a jittered k^3 lattice when particles_per_cell is a
cube k^3, else uniform random points, the same for the same seed); those inside the shape are kept.

Shape texts (scene.initial / scene.target with sim.dim = 3):
- a mesh file (.obj .stl .ply .off .glb), read with trimesh (meshes.py); its frame is its bounding box;
- "shape:NAME?key=value&...", a built-in solid in the unit cube [0, 1]^3 (its frame, so sizes are fractions
  of scene.region and two built-in shapes keep their relative sizes, as two images do):
    sphere       r = 0.3                        radius
    box          sx = sy = sz = 0.5             side lengths
    torus        R = 0.3, r = 0.12, axis = "z"  ring radius, tube radius, axis through the hole (x, y or z)
    two_spheres  r = 0.2, d = 0.5               radius of each, distance of their centres along x
  each also takes its centre cx = cy = cz = 0.5;
- "extrude:IMAGE?depth=0.25": a 2D image's material pixels (images.material) extruded along z into a slab
  depth times the image's larger side thick (the frame: width x height x that, in pixels); its particles take
  the pixel's colour.
Built-in shapes and meshes are black (0, 0, 0), like the shipped images' shapes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable
from urllib.parse import parse_qsl

import numpy as np

from .errors import UserError
from .images import box_cells, cell_samples, default_region, fit_box, lattice_side, load_image, material
from .meshes import contains, is_mesh_path, load_mesh

CENTRE = {"cx": 0.5, "cy": 0.5, "cz": 0.5}
SHAPES = {  # name -> parameters and their defaults (unit-cube units)
    "sphere": {"r": 0.3, **CENTRE},
    "box": {"sx": 0.5, "sy": 0.5, "sz": 0.5, **CENTRE},
    "torus": {"R": 0.3, "r": 0.12, "axis": "z", **CENTRE},
    "two_spheres": {"r": 0.2, "d": 0.5, **CENTRE},
}
EXTRUDE = {"depth": 0.25}  # slab thickness, a fraction of the image's larger side
AXES = ("x", "y", "z")
BLACK = (0.0, 0.0, 0.0)


class ShapeError(UserError):
    """A shape text or its file cannot be used; the message is one line."""


@dataclass(frozen=True)
class Solid:
    """A 3D shape: its frame [lo, hi] (fitted into scene.region), inside(p) for points p (n, 3) of the frame,
    color(p) (n, 3) RGB for points inside, and the box [bounds[0], bounds[1]] of the frame holding it."""

    lo: np.ndarray
    hi: np.ndarray
    inside: Callable
    color: Callable = lambda p: np.broadcast_to(np.asarray(BLACK), (len(p), 3))
    notes: tuple = field(default=())  # lines to print when it is used (a repaired mesh)
    bounds: tuple = None  # (lo, hi) of the shape inside its frame; None: the whole frame


def parse(text):
    """(kind, body, params) of a shape text: ("shape", NAME, {...}), ("extrude", IMAGE, {...}) or ("file", PATH,
    {}); the parameters checked and completed with their defaults."""
    text = str(text)
    for kind, known in (("shape", None), ("extrude", EXTRUDE)):
        if text.startswith(kind + ":"):
            body, _, query = text[len(kind) + 1:].partition("?")
            if kind == "shape":
                if body not in SHAPES:
                    raise ShapeError(f"unknown built-in shape {body!r}; expected one of "
                                     + ", ".join(f"shape:{n}" for n in SHAPES))
                known = SHAPES[body]
            if not body:
                raise ShapeError("extrude: expected an image path after 'extrude:'")
            return kind, body, _params(query, known, f"{kind}:{body}")
    return "file", text, {}


def _params(query, known, what):
    """key=value&... read against the known parameters and defaults: numbers > 0, or an axis name."""
    params = dict(known)
    for key, value in parse_qsl(query, keep_blank_values=True, strict_parsing=False) if query else ():
        if key not in known:
            raise ShapeError(f"{what}: unknown parameter {key!r}; expected " + ", ".join(known))
        if key == "axis":
            if value not in AXES:
                raise ShapeError(f"{what}: axis={value}: expected x, y or z")
            params[key] = value
            continue
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not (math.isfinite(number) and number > 0):
            raise ShapeError(f"{what}: {key}={value}: expected a number > 0")
        params[key] = number
    return params


def text_of(kind, body, params) -> str:
    """The canonical text of a parsed shape (every parameter written, in their documented order)."""
    if kind == "file":
        return str(body)
    query = "&".join(f"{k}={v if isinstance(v, str) else f'{v:g}'}" for k, v in params.items())
    return f"{kind}:{body}?{query}"


def builtin(name, params) -> Solid:
    """A built-in shape in the unit cube, refused when it does not lie inside it."""
    c = np.array([params["cx"], params["cy"], params["cz"]])
    if name == "sphere":
        r = params["r"]
        half, inside = np.full(3, r), lambda p: np.sum((p - c) ** 2, axis=1) < r * r
    elif name == "box":
        half = 0.5 * np.array([params["sx"], params["sy"], params["sz"]])
        inside = lambda p: np.all(np.abs(p - c) < half, axis=1)  # noqa: E731
    elif name == "torus":
        R, r, a = params["R"], params["r"], AXES.index(params["axis"])
        if r >= R:
            raise ShapeError(f"shape:torus: r={r:g}: expected a tube radius below the ring radius R={R:g}")
        half = np.full(3, R + r)
        half[a] = r

        def inside(p):
            q = p - c
            ring = np.sqrt(np.sum(np.delete(q, a, axis=1) ** 2, axis=1)) - R
            return ring ** 2 + q[:, a] ** 2 < r * r
    elif name == "two_spheres":
        r, d = params["r"], params["d"]
        if d <= 2 * r:
            raise ShapeError(f"shape:two_spheres: d={d:g}: expected a centre distance above 2 r = {2 * r:g} "
                             "(the spheres apart)")
        half = np.array([0.5 * d + r, r, r])
        offset = np.array([0.5 * d, 0.0, 0.0])
        inside = lambda p: np.minimum(np.sum((p - c - offset) ** 2, axis=1),  # noqa: E731
                                      np.sum((p - c + offset) ** 2, axis=1)) < r * r
    if np.any(c - half < 0) or np.any(c + half > 1):
        raise ShapeError(f"shape:{name}: spans {np.round(c - half, 4).tolist()} to {np.round(c + half, 4).tolist()}: "
                         "expected a shape inside the unit cube [0, 1]^3 (its frame); make it smaller or move its "
                         "centre cx, cy, cz")
    return Solid(np.zeros(3), np.ones(3), inside, bounds=(c - half, c + half))


def extruded(path, depth) -> Solid:
    """A 2D image's material pixels extruded along z: pixel (row r, col c) covers x in [c, c+1], y in
    [H-1-r, H-r] of the frame, and z in [0, depth * max(H, W)]."""
    rgba = load_image(path)
    mask = material(rgba)
    H, W = mask.shape
    if not mask.any():
        raise ShapeError(f"{path}: the image has no material pixels (opaque and not white)")
    D = depth * max(H, W)

    def pixel(p):
        col, row = np.floor(p[:, 0]).astype(np.int64), H - 1 - np.floor(p[:, 1]).astype(np.int64)
        ok = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (p[:, 2] >= 0) & (p[:, 2] < D)
        return np.clip(row, 0, H - 1), np.clip(col, 0, W - 1), ok

    def inside(p):
        row, col, ok = pixel(p)
        return ok & mask[row, col]

    def color(p):
        row, col, _ = pixel(p)
        return rgba[row, col, :3]

    return Solid(np.zeros(3), np.array([W, H, D], np.float64), inside, color)


def meshed(path, repair=False) -> Solid:
    """A watertight triangle mesh; its frame is its bounding box."""
    tri, notes = load_mesh(path, repair)
    flat = tri.reshape(-1, 3)
    return Solid(flat.min(axis=0), flat.max(axis=0), lambda p: contains(tri, p), notes=tuple(notes))


def solid(text, repair=False) -> Solid:
    """The Solid of a shape text (a mesh path, shape:NAME?..., extrude:IMAGE?...); paths as given."""
    kind, body, params = parse(text)
    if kind == "shape":
        return builtin(body, params)
    if kind == "extrude":
        return extruded(Path(body), params["depth"])
    if not is_mesh_path(body):
        raise ShapeError(f"{body}: expected a mesh (.obj .stl .ply .off .glb), shape:NAME or extrude:IMAGE")
    return meshed(Path(body), repair)


def particle_bound(s: Solid, n_grid, particles_per_cell, region=None, bound=3) -> int:
    """An upper bound of the particles `sample` keeps: particles_per_cell times the cells its bounds touch."""
    lo, hi, _, _ = _cells(s, n_grid, region, bound)
    return particles_per_cell * math.prod(int(h - l) for l, h in zip(lo, hi))


def _cells(s, n_grid, region, bound):
    """(lo, hi, origin, scale): the cells [lo, hi) the shape's bounds touch once its frame is fitted into region."""
    region = default_region(n_grid, bound, 3) if region is None else tuple(float(r) for r in region)
    origin, scale = fit_box(s.lo, s.hi, region)
    b_lo, b_hi = s.bounds if s.bounds is not None else (s.lo, s.hi)
    corner = [o + scale * (b - l) for o, b, l in zip(origin, b_lo, s.lo)]
    lo, hi = box_cells(corner, [scale * (h - l) for l, h in zip(b_lo, b_hi)], 1.0 / n_grid)
    return lo, hi, origin, scale


def sample(s: Solid, n_grid, particles_per_cell, region=None, seed=0, bound=3):
    """Particles inside the shape fitted into region: (x (N, 3), colors (N, 3)), deterministic for a seed.
    region (x0, y0, z0, x1, y1, z1) defaults to default_region(n_grid, bound, 3)."""
    lo, hi, origin, scale = _cells(s, n_grid, region, bound)
    dx = 1.0 / n_grid
    rng = np.random.default_rng(seed)
    xs, colors = [], []
    for x in cell_samples(lo, hi, particles_per_cell, dx, rng):
        p = s.lo + (x - np.asarray(origin)) / scale  # the frame's units
        keep = s.inside(p)
        xs.append(x[keep])
        colors.append(np.asarray(s.color(p[keep]), np.float64))
    x = np.concatenate(xs)
    if not len(x):
        k = lattice_side(particles_per_cell, 3) or 1
        raise ShapeError(f"no particle landed inside the shape; it is smaller than the particle spacing "
                         f"({dx / k:.3g}) at n_grid {n_grid}")
    return x, np.concatenate(colors)
