"""A scene made concrete: initial particles, the loss object and its target grids, and shape metrics.

`build(scene)` turns images (2D) or 3D shapes (shapes.py: meshes, built-in shapes, extruded images) into
particles (images.sample_particles, shapes.sample) and target grids on (res,)^dim loss grids (images.splat_grid);
the metrics (occupied, iou, mass_outside) compare a final mass grid with a target grid for summary.json.
Before anything large is allocated, build refuses a scene whose arrays would not fit in memory: the decoded
images (2D images and extruded ones; meshes are not counted), the sampled particles (an upper bound of their
number from the fitted shapes), the numpy target grids, then (memory.check_memory) the simulator's fields.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import memory
from .images import (DECODE_BYTES, ImageError, default_region, image_size, load_image, material, particle_bound,
                     pixel_of, sample_particles, splat_grid)
from .losses import ColorLoss, MassLoss, OTLoss, PositionLoss
from .memory import check_memory
from .meshes import MeshError
from .scene import SceneError
from . import shapes
from .scene_keys import toml_text

EMPTY = 1e-6  # a target node is empty where its mass is at most EMPTY times the grid's largest
OCCUPIED = 0.1  # a node is occupied (iou) where it holds more than this fraction of the rest node mass
WORD = 8  # bytes of a float64 entry
PARTICLE_WORDS = {2: 2 * (2 + 3), 3: 2 * (3 + 3)}  # float64 words per sampled particle, by dim: x (dim) and RGB (3),
# chunks and their concatenation
GRID_TEMPORARIES = 2  # float64 words per loss-grid node of temporaries while a target grid is made
PENALTY_IMAGE_WORDS = 6  # float64 words per loss-grid node while alpha is read from a penalty image


@dataclass
class Problem:
    """What a run optimizes. Grids are indexed [i, j(, k)] = node (i, j(, k)) / res, one per loss grid res."""

    x0: np.ndarray  # (N, dim) initial particle positions
    colors: np.ndarray  # (N, 3) initial particle RGB, from the initial image or shape
    loss: object  # PositionLoss, MassLoss, ColorLoss or OTLoss
    target_x: np.ndarray | None  # (N, dim) position-loss targets x_pu, or None
    target_mass_grids: list  # (res,) * dim target mass m_iu per loss grid (also for position and color losses)
    res: int  # the finest loss grid's resolution
    target_points: np.ndarray | None = None  # (M, dim) particles sampled on the target shape, or None
    target_colors: np.ndarray | None = None  # (M, 3) their RGB, or None
    alpha: list | None = None  # (res,) * dim penalty alpha_i per loss grid (eq 72), or None
    notes: tuple = ()  # lines for the run's output (a repaired mesh)


def rest_node_mass(cfg, res: int) -> float:
    """Mass of a res-grid node deep inside a body at rest density: density / res^dim (the B-spline integrates to
    dx^dim)."""
    return cfg.density / res ** cfg.dim


def occupied(mass_grid, rest_node_mass, frac=OCCUPIED) -> np.ndarray:
    """Bool grid of nodes holding more than frac of the rest node mass (the occupancy iou counts, 2D and 3D)."""
    return np.asarray(mass_grid) > frac * rest_node_mass


def iou(a, b) -> float:
    """Intersection over union of two bool grids (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def target_iou(mass, target, rest) -> float | None:
    """iou of the occupied nodes of a run's final mass grid and of its target (`occupied`), or None when no target
    node is occupied: a target whose mass (the body's, spread over its area) lies below OCCUPIED of the rest node
    mass everywhere has no region to compare with, and an empty body would read 1."""
    aim = occupied(target, rest)
    return iou(occupied(mass, rest), aim) if aim.any() else None


def iou_text(value) -> str:
    """target_iou for a line of output: 3 decimals, or why there is none."""
    if value is None:
        return (f"n/a (no target node holds {OCCUPIED:g} of the rest node mass: the target is too thin for the "
                "body's mass)")
    return f"{value:.3f}"


def empty(target) -> np.ndarray:
    """Bool grid of target nodes without mass (at most EMPTY times the largest target node mass)."""
    target = np.asarray(target, np.float64)
    return target <= EMPTY * target.max(initial=0.0)


def mass_outside(mass, target) -> float:
    """Fraction of the total mass lying on nodes where the target is empty (thesis 7.2: mass ejection)."""
    mass = np.asarray(mass, np.float64)
    total = mass.sum()
    return 0.0 if total <= 0 else float(mass[empty(target)].sum() / total)


def build(scene) -> Problem:
    """Sample the scene's shapes and make its loss object (thesis 5.4-5.6, 8.1, 8.2)."""
    cfg, ls = scene.sim, scene.loss
    images = {"scene.initial": scene.initial}
    if scene.target is not None:
        images["scene.target"] = scene.target
    if not isinstance(ls.penalty, (int, float)):
        images["loss.penalty"] = ls.penalty
    decoded = {key: _decode_bytes(scene, key, text) for key, text in images.items()}
    _check_memory(scene, decoded, 0)
    initial = _load(scene, "scene.initial", scene.initial)
    target = None if scene.target is None else _load(scene, "scene.target", scene.target)
    n_upper = _particle_bound(scene, initial)
    m_upper = 0 if target is None else _particle_bound(scene, target)
    _check_memory(scene, decoded, n_upper + m_upper)
    check_memory(cfg, n_upper, grids=loss_grids(ls), where=f"{scene.path}: ")

    x0, colors = _sample(scene, "scene.initial", initial)
    notes = tuple(n for shape in (initial, target) for n in getattr(shape, "notes", ()))
    if ls.kind == "position":
        centroid = x0.mean(axis=0)
        target_x = centroid + np.asarray(ls.target_scale) * (x0 - centroid) + np.asarray(ls.target_offset)
        lo, hi = cfg.dx, 1.0 - 2.0 * cfg.dx
        if np.any((target_x < lo) | (target_x >= hi)):
            raise SceneError(f"{scene.path}: loss.target_scale = {list(ls.target_scale)}, loss.target_offset = "
                             f"{list(ls.target_offset)}: expected target positions inside [{lo:.4g}, {hi:.4g}) "
                             f"(they span {target_x.min(axis=0).round(4).tolist()} to "
                             f"{target_x.max(axis=0).round(4).tolist()})")
        grids = [splat_grid(target_x, cfg.m_p, res) for res in ls.grids]
        return Problem(x0, colors, PositionLoss(target_x), target_x, grids, max(ls.grids), notes=notes)

    tx, tcolors = _sample(scene, "scene.target", target)
    if any(scene.target_shift):
        tx = tx + np.asarray(scene.target_shift)
        lo, hi = cfg.dx, 1.0 - 2.0 * cfg.dx
        if np.any((tx < lo) | (tx >= hi)):
            raise SceneError(f"{scene.path}: scene.target_shift = {list(scene.target_shift)}: expected a shift that "
                             f"keeps the target inside [{lo:.4g}, {hi:.4g}) (it spans "
                             f"{tx.min(axis=0).round(4).tolist()} to {tx.max(axis=0).round(4).tolist()})")
    m_t = target_particle_mass(scene, len(x0), len(tx))
    grids = [splat_grid(tx, m_t, res) for res in ls.grids]
    alpha = None
    if ls.kind == "color":
        targets = [splat_grid(tx, m_t, res, tcolors) for res in ls.grids]
        loss = ColorLoss(targets, colors, list(ls.weights), list(ls.ot_weights) or None, ls.ot_blur)
    elif ls.kind == "ot":
        loss = OTLoss(grids, list(ls.weights), ls.ot_blur, ls.ot_reach, list(ls.mass_weights) or None)
    else:
        if ls.penalty:
            alpha = [_alpha(scene, g) for g in grids]
        loss = MassLoss(grids, list(ls.weights), alpha, log=ls.kind == "log_mass")
    return Problem(x0, colors, loss, None, grids, max(ls.grids), tx, tcolors, alpha, notes)


def loss_grids(ls) -> list:
    """(res, channels, has_alpha) of each loss grid the simulator allocates for these [loss] settings."""
    if ls.kind == "position":
        return []
    channels = 3 if ls.kind == "color" else 1
    second = {"color": ls.ot_weights, "ot": ls.mass_weights}  # the grids' second term: colour transport, eq 11
    if ls.kind in second:  # a grid of each term whose weight is > 0, in the loss's order (first terms first)
        others = second[ls.kind] or (0.0,) * len(ls.grids)
        return [(res, channels, False) for weights in (ls.weights, others)
                for res, w in zip(ls.grids, weights) if w > 0]
    return [(res, channels, bool(ls.penalty)) for res in ls.grids]


def target_grid_bytes(ls, dim=2) -> int:
    """Bytes of the numpy target grids build makes: per node a mass (position and mass losses, and the metrics),
    three colour-mass channels (color loss), alpha (penalty; node positions and pixels for a penalty image),
    and temporaries."""
    image = not isinstance(ls.penalty, (int, float))
    words = 1 + (3 if ls.kind == "color" else 0) + (1 if ls.penalty else 0) + (PENALTY_IMAGE_WORDS if image else 0) \
        + GRID_TEMPORARIES
    return sum(res ** dim * words * WORD for res in ls.grids)


def target_particle_mass(scene, n_body, n_target) -> float:
    """Mass of one target particle: m_p, rescaled with target_density "match" so the totals are equal."""
    return scene.sim.m_p * (n_body / n_target if scene.target_density == "match" else 1.0)


def mass_error(mass, target) -> float:
    """Total-variation distance between two node-mass grids, relative to the target's mass:
    1/2 sum_i |m_i - m_iu| / sum_i m_iu (0: the same masses on every node; 1: disjoint, equal totals)."""
    mass, target = np.asarray(mass, np.float64), np.asarray(target, np.float64)
    total = target.sum()
    return 0.0 if total <= 0 else float(0.5 * np.abs(mass - target).sum() / total)


def color_error(color_mass, target) -> float:
    """The largest over the RGB channels of mass_error between two colour-mass grids (res, res, 3) (eq 12)."""
    return max(mass_error(color_mass[..., c], target[..., c]) for c in range(3))


def _check_memory(scene, images, particles):
    """Refuse, naming the largest part's key, when the decoded images (key -> bytes), the sampled particles
    (an upper bound of their number) and the numpy target grids would not fit."""
    limit, words = memory.limit(scene.sim)
    if limit is None:
        return
    ls, cfg = scene.loss, scene.sim
    parts = dict(images)
    parts["sim.n_grid"] = particles * PARTICLE_WORDS[cfg.dim] * WORD
    parts["loss.grids"] = target_grid_bytes(ls, cfg.dim)
    if sum(parts.values()) <= limit:
        return
    key = max(parts, key=parts.get)
    need = f"about {parts[key] / 2 ** 30:.3g} GiB"
    below = f"below the limit of {limit / 2 ** 30:.3g} GiB ({words})"
    if key == "loss.grids":
        sizes = ", ".join(f"{res}^{cfg.dim}" for res in ls.grids)
        default = " (sim.n_grid when loss.grids is not set)" if ls.grids == (cfg.n_grid,) else ""
        raise SceneError(f"{scene.path}: loss.grids = {toml_text(list(ls.grids))}{default}: expected loss grids whose "
                         f"target arrays fit in memory ({need} for {sizes} nodes), {below}")
    if key == "sim.n_grid":
        raise SceneError(f"{scene.path}: sim.n_grid = {cfg.n_grid}, sim.particles_per_cell = {cfg.particles_per_cell}: "
                         f"expected particles that fit in memory (up to {particles}, {need} while sampled), {below}; "
                         "lower sim.n_grid or sim.particles_per_cell")
    raise SceneError(f"{scene.path}: {key}: expected an image that fits in memory when decoded ({need}), {below}")


def _decode_bytes(scene, key, text):
    """Bytes of one image (2D, or extruded in 3D) while it is decoded, from its header; 0 for other 3D shapes."""
    if scene.sim.dim == 3 and key != "loss.penalty":
        kind, path, _ = shapes.parse(text)
        if kind != "extrude":
            return 0
        text = path
    width, height = _worded(scene, key, text, image_size)
    return width * height * DECODE_BYTES


def _load(scene, key, text):
    """A shape of the scene: an image as (H, W, 4) float RGBA (2D), or a shapes.Solid (3D)."""
    if scene.sim.dim == 3 and key != "loss.penalty":
        try:
            return shapes.solid(text, repair=scene.repair)
        except (ImageError, MeshError, shapes.ShapeError) as e:
            raise SceneError(f"{scene.path}: {key} = \"{text}\": expected a usable 3D shape ({e})") from None
    return _worded(scene, key, text, load_image)


def _worded(scene, key, path, read):
    """read(path), with image errors worded as scene errors."""
    try:
        return read(path)
    except ImageError as e:
        raise SceneError(f"{scene.path}: {key} = \"{path}\": expected an image file ({e})") from None


def _particle_bound(scene, shape):
    cfg = scene.sim
    if cfg.dim == 3:
        return shapes.particle_bound(shape, cfg.n_grid, cfg.particles_per_cell, scene.region, bound=cfg.bound)
    return particle_bound(material(shape), cfg.n_grid, cfg.particles_per_cell, scene.region, bound=cfg.bound)


def _sample(scene, key, shape):
    """Particles of one of the scene's shapes (an image's RGBA, or a 3D shapes.Solid), with sampling errors
    worded as scene errors."""
    cfg = scene.sim
    sample = shapes.sample if cfg.dim == 3 else sample_particles
    try:
        return sample(shape, cfg.n_grid, cfg.particles_per_cell, scene.region, scene.seed, bound=cfg.bound)
    except (ImageError, shapes.ShapeError) as e:
        path = scene.initial if key == "scene.initial" else scene.target
        what = "a shape that holds at least one particle" if cfg.dim == 3 else "an image with material"
        raise SceneError(f"{scene.path}: {key} = \"{path}\": expected {what} ({e})") from None


def _alpha(scene, target):
    """Penalty alpha_i on one loss grid (eq 72): a number on empty target nodes, or sampled from an image."""
    res = target.shape[0]
    ls = scene.loss
    if not isinstance(ls.penalty, (int, float)):
        rgba = _load(scene, "loss.penalty", ls.penalty)
        gray = rgba[..., :3].mean(axis=-1) * rgba[..., 3] + (1.0 - rgba[..., 3])  # transparent reads as white
        nodes = np.stack(np.meshgrid(np.arange(res), np.arange(res), indexing="ij"), -1).reshape(-1, 2) / res
        region = scene.region or default_region(scene.sim.n_grid, scene.sim.bound)
        row, col, _ = pixel_of(nodes, gray.shape, region)  # nodes beyond the image take the nearest pixel
        return (1.0 + gray[row, col] * (ls.penalty_max - 1.0)).reshape(res, res)
    return np.where(empty(target), float(ls.penalty), 1.0)

