"""A scene made concrete: initial particles, the loss object and its target grids, and shape metrics.

`build(scene)` turns images into particles (images.sample_particles) and target grids (images.splat_grid);
the metrics (occupied, iou, mass_outside) compare a final mass grid with a target grid for summary.json.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import ImageError, default_region, load_image, pixel_of, sample_particles, splat_grid
from .losses import ColorLoss, MassLoss, PositionLoss
from .scene import SceneError

EMPTY = 1e-6  # a target node is empty where its mass is at most EMPTY times the grid's largest


@dataclass
class Problem:
    """What a run optimizes. Grids are indexed [i, j] = node (i / res, j / res), one per loss grid res."""

    x0: np.ndarray  # (N, 2) initial particle positions
    colors: np.ndarray  # (N, 3) initial particle RGB, from the initial image
    loss: object  # PositionLoss, MassLoss or ColorLoss
    target_x: np.ndarray | None  # (N, 2) position-loss targets x_pu, or None
    target_mass_grids: list  # (res, res) target mass m_iu per loss grid (also for position and color losses)
    res: int  # the finest loss grid's resolution
    target_points: np.ndarray | None = None  # (M, 2) particles sampled on the target image, or None
    target_colors: np.ndarray | None = None  # (M, 3) their RGB, or None
    alpha: list | None = None  # (res, res) penalty alpha_i per loss grid (eq 72), or None

    @property
    def finest_res(self) -> int:
        """Alias of res."""
        return self.res


def rest_node_mass(cfg, res: int) -> float:
    """Mass of a res-grid node deep inside a body at rest density: density / res^2 (the B-spline integrates to dx^2)."""
    return cfg.density / res ** 2


def occupied(mass_grid, rest_node_mass, frac=0.1) -> np.ndarray:
    """Bool grid of nodes holding more than frac of the rest node mass."""
    return np.asarray(mass_grid) > frac * rest_node_mass


def iou(a, b) -> float:
    """Intersection over union of two bool grids (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


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
    """Sample the scene's images and make its loss object (thesis 5.4-5.6, 8.1, 8.2)."""
    cfg, ls = scene.sim, scene.loss
    x0, colors = _sample(scene, "scene.initial", scene.initial)
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
        return Problem(x0, colors, PositionLoss(target_x), target_x, grids, max(ls.grids))

    tx, tcolors = _sample(scene, "scene.target", scene.target)
    m_t = cfg.m_p * (len(x0) / len(tx) if scene.target_density == "match" else 1.0)
    grids = [splat_grid(tx, m_t, res) for res in ls.grids]
    alpha = None
    if ls.kind == "color":
        targets = [splat_grid(tx, m_t, res, tcolors) for res in ls.grids]
        loss = ColorLoss(targets, colors, list(ls.weights))
    else:
        if ls.penalty:
            alpha = [_alpha(scene, g) for g in grids]
        loss = MassLoss(grids, list(ls.weights), alpha, log=ls.kind == "log_mass")
    return Problem(x0, colors, loss, None, grids, max(ls.grids), tx, tcolors, alpha)


def _sample(scene, key, path):
    """Particles of one of the scene's images, with image errors worded as scene errors."""
    try:
        return sample_particles(load_image(path), scene.sim.n_grid, scene.sim.particles_per_cell, scene.region,
                                scene.seed, bound=scene.sim.bound)
    except ImageError as e:
        raise SceneError(f"{scene.path}: {key} = \"{path}\": expected an image with material ({e})") from None


def _alpha(scene, target):
    """Penalty alpha_i on one loss grid (eq 72): a number on empty target nodes, or sampled from an image."""
    res = target.shape[0]
    ls = scene.loss
    if not isinstance(ls.penalty, (int, float)):
        rgba = load_image(ls.penalty)
        gray = rgba[..., :3].mean(axis=-1) * rgba[..., 3] + (1.0 - rgba[..., 3])  # transparent reads as white
        nodes = np.stack(np.meshgrid(np.arange(res), np.arange(res), indexing="ij"), -1).reshape(-1, 2) / res
        region = scene.region or default_region(scene.sim.n_grid, scene.sim.bound)
        row, col, _ = pixel_of(nodes, gray.shape, region)  # nodes beyond the image take the nearest pixel
        return (1.0 + gray[row, col] * (ls.penalty_max - 1.0)).reshape(res, res)
    return np.where(empty(target), float(ls.penalty), 1.0)

