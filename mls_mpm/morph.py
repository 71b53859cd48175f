"""`mls-mpm morph INITIAL TARGET`: a complete scene chosen from two shapes, no scene file needed.

The choices, each written into the scene file the run saves (DIR/scene.toml), so `mls-mpm run DIR/scene.toml`
reproduces the run and a user can edit it:
- the target is moved so that its centre of mass is the body's (scene.target_shift; `--keep-position` keeps
  it where the image puts it): the controls are internal forces and cannot move the body's centre of mass;
- the thesis program's material on the grid of the quality preset (E = 90000 dx^2, nu 0.3, density 40, drag
  0.5, dt = 1/120, no gravity: the shipped thesis scenes' settings at any n_grid);
- steps long enough for the distance the mass has to travel: the optimal assignment of a subsample of the
  initial particles to as many target particles (scipy's linear_sum_assignment, the exact discrete transport
  plan) gives every particle's distance; the plan's 90th percentile d is travelled at a peak speed of
  SPEED cells per step (half a cell: inside the CFL limit of one cell), accelerating and braking, in
  2 d / speed steps, plus SETTLE steps to come to rest, rounded up to the control stride, within
  [MIN_STEPS, MAX_STEPS];
- the loss: optimal transport (loss.kind = "ot") on the coarse grid, which pulls material wherever it is,
  and the eq 11 mass loss on the fine grid, which shapes the detail; each term weighted by 1 / its value at
  rest, so both start at 1 whatever the shapes' sizes; a coarse stage (OT alone) first, then both
  (optimize.schedule; a coarse stage that leaves the sum above its start is dropped, schedule._kept: capsule to a
  thin ring at --quality fast, 24^3, had torn into three blobs, iou 0.18, and reaches 0.60 without that stage).
  Colour images (`--loss color`, or two images of more than one colour region each): the transport of each
  colour channel's colour-mass on the coarse grid and eq 13 on the fine one, both from the first iteration (a
  coarse stage of colour transport alone left color_swap's colours scrambled: iou 0.36 against 0.87 without it);
- L-BFGS, the quality's iteration count and time budget (optimize.max_seconds); at default quality three rounds
  and at best two (3D: two at fast, three at both others; optimize.rounds): each round starts at rest from where
  the one before ended and optimizes again, which finishes what one long optimization stalls on (a square into a
  thin L at default: iou 0.61 in one round, 0.84-0.94 in two, 0.96-0.98 in three, BENCHMARKS.md).

In 3D (sim.dim = 3: INITIAL or TARGET a mesh, "shape:..." or "extrude:IMAGE", shapes.py; or dim=3) the same
choices are made on the 3D quality's grid (QUALITIES_3D: 32^3 at default) with 1 particle per cell volume, no
gravity along any axis, and the colour test on the sampled particles' colours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from . import shapes
from .errors import UserError
from .images import ImageError, check_image, load_image, material, sample_particles, splat_grid
from .meshes import MeshError, is_mesh_path
from .problem import OCCUPIED
from .losses import COLOR_EMPTY, OT_BLUR
from .ot import sinkhorn_divergence
from .scene_keys import NAME_MAX, parse_override, toml_text, valid_name

SPEED = 0.5  # peak material speed, cells per step (0.25 left thin strokes short of iterations: steps cost time)
SETTLE = 40  # steps after the travel for the body to come to rest
MIN_STEPS, MAX_STEPS = 100, 400
PLAN_SAMPLES = 600  # particles of each shape in the transport plan that sets the number of steps
PLAN_QUANTILE = 0.9  # the distance of the plan the steps are made for
E_CELLS = 90000.0  # the thesis program's Young's modulus in cell units; E = E_CELLS dx^2
DT = 1.0 / 120.0
STRIDE = 10
COLOR_SHARE = 0.05  # a colour region holds at least this fraction of an image's material pixels
COLOR_LEVELS = 4  # levels per channel when colours are counted
FEW_PARTICLES = 50  # an INITIAL sampled into fewer particles than this barely deforms: choose notes it
FRAMED = 0.9  # an image whose border is material (not white) for more than this fraction looks like a mask drawn
# the other way round (a white shape on black): choose notes it
AREA_RATIO = 4.0  # target / initial area (3D: volume) beyond which, or below whose inverse, choose notes the change
# of density the body's fixed mass must take (the quality suite's pairs go to 3 and 1/3 and reach iou >= 0.9)


@dataclass(frozen=True)
class Quality:
    n_grid: int  # simulation grid; the fine loss grid is the same, the coarse one half of it
    iterations: int  # L-BFGS iterations over all stages
    max_seconds: float  # the default time budget (0: none), shared by the rounds
    particles_per_cell: int = 4
    rounds: int = 1  # optimize.rounds: each round starts at rest from where the one before ended (thesis 7.4)


QUALITIES = {
    "fast": Quality(n_grid=32, iterations=120, max_seconds=25.0),
    # more rounds, each starting at rest from where the one before ended, finish what one long optimization stalls
    # on (thin strokes tearing, colours that flow past each other): three in the same budget raised the worst pairs
    # of bench quality (letter_L_thin 0.90 -> 0.96, color_bar_to_disk 0.92 -> 0.98) and lowered none (BENCHMARKS.md
    # "Morph quality"); best (no budget) keeps the two rounds it was measured with
    "default": Quality(n_grid=64, iterations=400, max_seconds=105.0, rounds=3),
    "best": Quality(n_grid=64, iterations=800, max_seconds=0.0, rounds=2),
}
QUALITIES_3D = {  # 3D: n_grid^3 nodes and a 4^3 stencil cost more a step, so a coarser grid and 1 particle per cell
    # fast: two rounds of 30 iterations: on the 11 pairs of `bench quality --dim 3`, iou 0.84-1.00 in 17-34 s against
    # 0.60-1.00 in 15-29 s for one round (a thin ring 0.60 -> 0.84, the colour slab 0.74 -> 0.89; BENCHMARKS.md)
    "fast": Quality(n_grid=24, iterations=30, max_seconds=120.0, particles_per_cell=1, rounds=2),
    # three rounds in 2D's two minutes, as in 2D: on six pairs of shapes not in the repository (BENCHMARKS.md "3D
    # morphs of shapes from outside the repository") iou 0.90-0.99, against 0.66-0.96 for one round of 60
    # iterations, which stopped at its iteration count after 38-65 s of its 300
    "default": Quality(n_grid=32, iterations=150, max_seconds=120.0, particles_per_cell=1, rounds=3),
    "best": Quality(n_grid=32, iterations=150, max_seconds=0.0, particles_per_cell=1, rounds=3),
}


class MorphError(UserError):
    """Bad input to `mls-mpm morph`: one line naming the file or option."""


@dataclass(frozen=True)
class Choice:
    """The scene text and what the choices were made from (for the one-line report)."""

    text: str
    name: str
    distance: float  # the plan's PLAN_QUANTILE distance, domain units
    speed: float  # peak speed, domain units per second
    steps: int
    loss: str
    shift: tuple = (0.0, 0.0)  # the target's move onto the body's centre of mass
    rounds: int = 1
    notes: tuple = ()  # lines on inputs the morph cannot serve well (framed_notes, size_notes)

    def line(self, q: str) -> str:
        moved = (f"target moved by ({', '.join(f'{v:+.3f}' for v in self.shift)}) onto the body's centre of mass "
                 "(--keep-position: not); " if any(self.shift) else "")
        return (f"morph ({q}): {moved}{self.loss} loss; travel {self.distance:.3f} (90% of the transport plan) at "
                f"up to {self.speed:.3g}/s (CFL-safe {SPEED} cell/step) -> {self.steps} steps"
                + (f" a round, {self.rounds} rounds" if self.rounds > 1 else ""))


def _image(path, what):
    p = Path(path).expanduser()
    try:
        check_image(p)
        rgba = load_image(p)
    except ImageError as e:
        raise MorphError(f"{what} {path}: expected an image file ({str(e).split(': ', 1)[-1]})") from None
    if not material(rgba).any():
        raise MorphError(f"{what} {path}: the image has no material (opaque, non-white pixels); expected a shape")
    return p.resolve(), rgba


def is_3d(text) -> bool:
    """Whether a morph input names a 3D shape: a mesh file, "shape:..." or "extrude:IMAGE"."""
    return str(text).startswith(("shape:", "extrude:")) or is_mesh_path(text)


def _shape(text, what, repair=False):
    """(canonical text with absolute paths, Solid) of a 3D morph input; paths relative to the working directory.
    repair: `--set scene.repair=true`, trimesh's fill_holes on a mesh that is not watertight."""
    try:
        kind, body, params = shapes.parse(text)
        if kind != "shape":
            body = Path(body).expanduser().resolve()
        return shapes.text_of(kind, body, params), shapes.solid(shapes.text_of(kind, body, params), repair)
    except (ImageError, MeshError, shapes.ShapeError) as e:
        raise MorphError(f"{what} {text}: expected a 3D shape ({e})") from None


def color_regions(rgba) -> int:
    """How many colours hold at least COLOR_SHARE of the material pixels (colours quantised per channel)."""
    return colour_count(rgba[material(rgba)][:, :3])


def colour_count(rgb) -> int:
    """How many colours hold at least COLOR_SHARE of the colours rgb (n, 3) (quantised per channel)."""
    q = np.minimum((rgb * COLOR_LEVELS).astype(int), COLOR_LEVELS - 1)
    _, counts = np.unique(q[:, 0] * COLOR_LEVELS ** 2 + q[:, 1] * COLOR_LEVELS + q[:, 2], return_counts=True)
    return int(np.count_nonzero(counts >= COLOR_SHARE * len(rgb)))


def _overrides(sets):
    """--set values as {(section, key): value}, parsed as in a scene (errors name the --set)."""
    return {(s, k): v for s, k, v in (parse_override(t) for t in sets)}


def travel_distance(x0, xt, seed=0) -> float:
    """The PLAN_QUANTILE distance of the exact transport plan between two particle sets.

    Sets larger than PLAN_SAMPLES are subsampled, and a plan between two random subsets carries their own gap
    even where nothing moves; that floor (the same quantile of the plan between two disjoint subsamples of x0)
    is taken off, so two identical sets give 0 and a translated set its translation.
    """
    rng = np.random.default_rng(seed)
    n = min(PLAN_SAMPLES, len(x0), len(xt))
    a = x0[rng.choice(len(x0), n, replace=False)]
    b = xt[rng.choice(len(xt), n, replace=False)]
    d = _plan_quantile(a, b)
    if n == len(x0) == len(xt):
        return d
    half = min(n, len(x0) // 2)
    picked = rng.permutation(len(x0))
    floor = _plan_quantile(x0[picked[:half]], x0[picked[half:2 * half]])
    return max(d - floor, 0.0)


def _plan_quantile(a, b) -> float:
    """PLAN_QUANTILE of the distances of the optimal assignment of a to b (scipy's linear_sum_assignment)."""
    from scipy.optimize import linear_sum_assignment

    cost = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    rows, cols = linear_sum_assignment(cost)
    return float(np.quantile(np.sqrt(cost[rows, cols]), PLAN_QUANTILE))


def centring_shift(x0, xt, n_grid, bound=3) -> np.ndarray:
    """The shift of the target particles xt that puts their centroid on the body's, limited so that they stay
    at least bound + 1 cells from every edge: the controls are internal forces, which cannot move the body's
    centre of mass (momentum is conserved; drag only slows it), so a target elsewhere cannot be reached."""
    shift = x0.mean(axis=0) - xt.mean(axis=0)
    dx = 1.0 / n_grid
    lo, hi = (bound + 1) * dx - xt.min(axis=0), 1.0 - (bound + 2) * dx - xt.max(axis=0)
    return np.clip(shift, np.minimum(lo, 0.0), np.maximum(hi, 0.0))


def choose(initial, target, quality="default", loss="auto", seconds=None, sets=(), keep_position=False,
           dim=None) -> Choice:
    """The scene for morphing image (or 3D shape) `initial` into `target` (MorphError on bad input).

    dim: 2 or 3; None: 3 when either names a 3D shape (is_3d), else 2."""
    dim = dim or (3 if is_3d(initial) or is_3d(target) else 2)
    if quality not in QUALITIES:
        raise MorphError(f"--quality {quality}: expected one of {', '.join(QUALITIES)}")
    q = (QUALITIES_3D if dim == 3 else QUALITIES)[quality]
    given = _overrides(sets)
    if dim == 3:  # src: a Solid (3D) or an RGBA image (2D), and how it is sampled
        repair = given.get(("scene", "repair")) is True  # a bad value: load_scene says so
        (p0, src0), (pt, srct) = _shape(initial, "INITIAL", repair), _shape(target, "TARGET", repair)
        sample = shapes.sample
    else:
        (p0, src0), (pt, srct) = _image(initial, "INITIAL"), _image(target, "TARGET")
        sample = sample_particles
    n = given.get(("sim", "n_grid"), q.n_grid)
    n = n if isinstance(n, int) and not isinstance(n, bool) and n >= 2 else q.n_grid  # a bad one: load_scene says so
    ppc = given.get(("sim", "particles_per_cell"), q.particles_per_cell)
    ppc = ppc if isinstance(ppc, int) and 1 <= ppc <= 1024 else q.particles_per_cell
    sampled = []
    for what, text, src in (("INITIAL", initial, src0), ("TARGET", target, srct)):
        try:
            sampled.append(sample(src, n, ppc))
        except (ImageError, shapes.ShapeError) as e:
            raise MorphError(f"{what} {text}: {e}; use a larger shape or a finer --set sim.n_grid") from None
    (x0, c0), (xt, ct) = sampled
    shift = np.zeros(dim) if keep_position else centring_shift(x0, xt, n)
    xt = xt + shift
    regions = (colour_count(c0), colour_count(ct)) if dim == 3 else (color_regions(src0), color_regions(srct))
    use_color = loss == "color" or (loss == "auto" and min(regions) > 1)
    dx = 1.0 / n
    distance = travel_distance(x0, xt)
    speed = SPEED * dx / DT
    steps = 2.0 * distance / (SPEED * dx) + SETTLE
    steps = int(min(max(STRIDE * math.ceil(steps / STRIDE), MIN_STEPS), MAX_STEPS))
    density = 40.0
    m_p = density * dx ** dim / ppc
    m_t = m_p * len(x0) / len(xt)
    coarse, fine = max(8, n // 2), n
    sections = {
        "scene": {"name": _name(p0, pt), "initial": str(p0), "target": str(pt),
                  "target_shift": [float(f"{v:.6g}") for v in shift]},
        "sim": {**({"dim": 3} if dim == 3 else {}), "n_grid": n, "steps": steps, "dt": DT, "E": E_CELLS * dx * dx,
                "nu": 0.3, "density": density, "gamma": 0.5, "gravity": [0.0] * dim, "particles_per_cell": ppc},
        "control": {"stride": STRIDE},
        "optimize": {"method": "lbfgs", "iterations": q.iterations,
                     "max_seconds": q.max_seconds if seconds is None else float(seconds),
                     **({"rounds": q.rounds} if q.rounds > 1 else {})},
    }
    if use_color:
        color_value = 0.5 * float(np.sum((splat_grid(x0, m_p, fine, c0) - splat_grid(xt, m_t, fine, ct)) ** 2))
        body, aim = splat_grid(x0, m_p, coarse, c0), splat_grid(xt, m_t, coarse, ct)
        ot_value = sum(sinkhorn_divergence(body[..., c], aim[..., c], OT_BLUR / coarse).value for c in range(3)
                       if body[..., c].sum() > COLOR_EMPTY * body.sum() and aim[..., c].sum() > COLOR_EMPTY * aim.sum())
        kind = "colour transport + colour"
        sections["loss"] = {"kind": "color", "grids": [coarse, fine], "weights": [0.0, _weight(color_value)],
                            "ot_weights": [_weight(ot_value), 0.0], "ot_blur": OT_BLUR}
    else:
        kind = "ot + mass"
        ot_value = sinkhorn_divergence(splat_grid(x0, m_p, coarse), splat_grid(xt, m_t, coarse),
                                       OT_BLUR / coarse).value
        mass_value = 0.5 * float(np.sum((splat_grid(x0, m_p, fine) - splat_grid(xt, m_t, fine)) ** 2))
        sections["loss"] = {"kind": "ot", "grids": [coarse, fine], "weights": [_weight(ot_value), 0.0],
                            "mass_weights": [0.0, _weight(mass_value)], "ot_blur": OT_BLUR}
    if not use_color:  # colours: both terms from the start (the colour transport alone scrambles what eq 13 then fixes)
        sections["optimize"]["schedule"] = [{"grids": [coarse], "share": 1.0},
                                            {"grids": [coarse, fine], "share": 2.0}]
    for (section, key), value in given.items():
        sections.setdefault(section, {})[key] = value
    text = _toml(sections, quality, kind)
    rounds = sections["optimize"].get("rounds", 1)  # a bad --set value: load_scene says so
    return Choice(text, sections["scene"]["name"], distance, speed, steps, kind, tuple(shift),
                  rounds if isinstance(rounds, int) and not isinstance(rounds, bool) else 1,
                  (() if dim == 3 else framed_notes(initial, src0, target, srct))
                  + size_notes(initial, target, len(x0), len(xt), n, dim))


def framed_notes(initial, rgba0, target, rgbat) -> tuple:
    """A note for each image whose border is nearly all material (more than FRAMED of its border pixels): its shape
    is then the image less its white part, which is what a white shape on black (a mask) gives."""
    notes = []
    for what, path, rgba in (("INITIAL", initial, rgba0), ("TARGET", target, rgbat)):
        border = material(np.concatenate([rgba[0], rgba[-1], rgba[1:-1, 0], rgba[1:-1, -1]]))
        if border.mean() > FRAMED:
            notes.append(f"note: {what} {path}: {border.mean():.0%} of its border is material (opaque, not white), "
                         f"so the shape is everything but its white part ({material(rgba).mean():.0%} of the "
                         "image); if the shape is the white part (a white-on-black mask), invert the image")
    return tuple(notes)


def size_notes(initial, target, n_initial, n_target, n_grid, dim) -> tuple:
    """Notes on a pair the morph will run but cannot serve well, from the particle counts of the two shapes sampled
    at one spacing (so in proportion to their areas, or volumes in 3D): an INITIAL of fewer than FEW_PARTICLES, and
    a TARGET more than AREA_RATIO times larger or smaller. The body's mass is fixed (the target grid holds the same
    mass), so a larger target is reached only at a lower density and a smaller one by compressing the body."""
    what = "area" if dim == 2 else "volume"
    grid = "x".join([str(n_grid)] * dim)
    counts = f"{n_target} against {n_initial} particles at one spacing"
    notes = []
    if n_initial < FEW_PARTICLES:
        notes.append(f"note: INITIAL {initial} gives only {n_initial} particles on the {grid} grid: a body this small "
                     "can barely deform; draw it larger, or use a finer --set sim.n_grid")
    ratio = n_target / n_initial
    if ratio > AREA_RATIO:
        notes.append(f"note: TARGET {target} has {ratio:.3g}x the {what} of INITIAL ({counts}): the body keeps its "
                     f"mass, so it can cover the target only at 1/{ratio:.3g} of its density (iou counts nodes above "
                     f"{OCCUPIED:g} of it); shapes of similar {what} morph more faithfully")
    elif ratio < 1.0 / AREA_RATIO:
        notes.append(f"note: TARGET {target} has 1/{1.0 / ratio:.3g} of the {what} of INITIAL ({counts}): the body "
                     f"would have to compress {1.0 / ratio:.3g}x, which its elastic material resists, so expect mass "
                     f"outside the target; shapes of similar {what} morph more faithfully")
    return tuple(notes)


def _weight(value) -> float:
    """1 / value, to 4 significant digits (1 for a term that is already zero)."""
    return float(f"{1.0 / value:.4g}") if value > 0 else 1.0


def _name(p0, pt) -> str:
    stem = lambda p: (shapes.parse(p)[1] if str(p).startswith("shape:") else Path(shapes.parse(p)[1]).stem)  # noqa: E731
    name = f"morph_{stem(p0)}_to_{stem(pt)}"
    name = "".join(c if c.isalnum() or c in "_.-" else "_" for c in name)[:NAME_MAX]
    return name if valid_name(name) else "morph"


def _toml(sections, quality, kind) -> str:
    lines = [f"# Written by `mls-mpm morph --quality {quality}` ({kind} loss); `mls-mpm run` this file to reproduce "
             "the run, or edit it (keys: scenes/README.md)."]
    for section, table in sections.items():
        lines.append(f"\n[{section}]")
        lines += [f"{key} = {toml_text(value)}" for key, value in table.items()]
    return "\n".join(lines) + "\n"
