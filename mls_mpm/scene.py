"""Scene files: TOML data validated when loaded; every key and default is listed in scenes/README.md.

A scene has the sections [scene], [sim], [control], [loss], [optimize] and [render]. `load_scene` checks every
key's type and range (the readers in scene_keys.py) and how keys combine, and refuses anything else with one
line: `<file>: <section.key> = <value>: expected <what>`.
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .config import CFLWarning, ConfigError, SimConfig, min_n_grid
from .export3d import MODES_3D
from .scene_keys import (NAME_RULE, RENDER_BACKGROUNDS, RENDER_MODES, RENDER_SIZE_MAX, RENDER_SIZE_MIN, SPEC,
                         SceneError, toml_text, Reader, parse_override, valid_name)

__all__ = ["RENDER_BACKGROUNDS", "RENDER_MODES", "RENDER_SIZE_MAX", "RENDER_SIZE_MIN", "SPEC", "LossSettings",
           "OptimizeSettings", "RenderSettings", "Scene", "SceneError", "load_scene", "parse_override"]


@dataclass(frozen=True)
class LossSettings:
    """[loss]: which loss, on which grids (thesis 5.4-5.6, 8.1, 8.2)."""

    kind: str = "mass"
    grids: tuple = ()  # loss grid resolutions; () in the dataclass, (n_grid,) once loaded
    weights: tuple = ()  # one per grid
    penalty: float | Path = 0.0  # 0: none; >= 1: alpha on empty target nodes; or a grayscale image
    penalty_max: float = 10.0  # alpha of a white penalty-image pixel (black: 1)
    target_scale: tuple = (1.0, 1.0)  # position loss: x_u = centroid + scale (x0 - centroid) + offset
    target_offset: tuple = (0.0, 0.0)
    ot_blur: float = 2.0  # ot: entropic blur sigma in cells of each loss grid
    ot_reach: float | None = None  # ot: None (balanced) or the unbalanced reach in domain units
    mass_weights: tuple = ()  # ot: weight of eq 11 on each loss grid beside the transport cost (0: none)
    ot_weights: tuple = ()  # color: weight of the per-channel transport cost on each loss grid (0: none)


@dataclass(frozen=True)
class OptimizeSettings:
    """[optimize]: the optimizer and its stopping rule (thesis 4.2, 7.3, 7.4, 8.1)."""

    method: str = "gd"
    iterations: int = 10
    step: str = "normalized"
    lr: float = 0.1
    line_search: int = 15
    tol: float = 1e-3
    rounds: int = 1
    carry_state: bool = False
    clip: float = 0.0
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999
    schedule: tuple = ()  # stages {"grids": (res, ...), "share": s}, coarse first (mls_mpm/schedule.py); (): one
    max_seconds: float = 0.0  # wall-clock budget of the run up to its result, compile included; 0: none


@dataclass(frozen=True)
class RenderSettings:
    """[render]: frames and animations written by a run (thesis 7.1)."""

    every: int = 5
    size: int = 512
    mode: str = "mass"  # 2D: mass | color | particles; 3D: surface | volume | particles (mass, color: surface)
    gif: bool = True
    mp4: bool = True  # animation.mp4 through imageio-ffmpeg's ffmpeg
    outline: bool = False
    background: str = "white"  # 2D PNG frames: "white", or "transparent" (an alpha channel, for compositing)


@dataclass(frozen=True)
class Scene:
    """A loaded, validated scene; paths are absolute, sim holds [sim] and control.stride."""

    name: str
    path: Path
    initial: Path | str  # an image or mesh path, or a shape text (shapes.py, 3D)
    target: Path | str | None
    region: tuple | None
    seed: int
    target_density: str
    sim: SimConfig
    loss: LossSettings
    optimize: OptimizeSettings
    render: RenderSettings
    target_shift: tuple = (0.0, 0.0)  # moves the target particles (domain units), e.g. onto the body's centroid
    repair: bool = False  # 3D: try trimesh's fill_holes on a mesh that is not watertight

    def to_dict(self) -> dict:
        """Every setting as plain JSON-able data, laid out like the scene file (for summary.json)."""
        sim = asdict(self.sim)
        stride = sim.pop("stride")
        loss = asdict(self.loss)
        return _plain({
            "scene": {"name": self.name, "path": self.path, "initial": self.initial, "target": self.target,
                      "region": self.region, "seed": self.seed, "target_density": self.target_density,
                      "target_shift": self.target_shift, "repair": self.repair},
            "sim": sim,
            "control": {"stride": stride},
            "loss": loss,
            "optimize": asdict(self.optimize),
            "render": asdict(self.render),
        })


def _plain(v):
    """Tuples -> lists, Paths -> str, recursively."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (tuple, list)):
        return [_plain(x) for x in v]
    if isinstance(v, Path):
        return str(v)
    return v


def load_scene(path, overrides=()) -> Scene:
    """Read and validate a scene file, after applying --set overrides "section.key=value"."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        if not path.exists():
            raise SceneError(f"{path}: no such scene file")
        what = "is a directory" if path.is_dir() else "is not a regular file (a device, pipe or socket)"
        raise SceneError(f"{path}: {what}; expected a scene file (TOML)")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a leading byte order mark is allowed
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not valid TOML ({' '.join(str(e).split())})") from None
    except OSError as e:
        raise SceneError(f"{path}: cannot be read ({e.strerror or e})") from None
    from_set = set()
    for text in overrides:
        section, key, value = parse_override(text)
        table = raw.setdefault(section, {})
        if not isinstance(table, dict):
            raise SceneError(f"{path}: --set {text!r}: {section} is not a [section] table")
        table[key] = value
        from_set.add((section, key))
    r = Reader(path, raw, from_set)
    r.check_names()

    # [sim] and [control]
    values = {key: r.get("sim", key) for key in SPEC["sim"]}
    values["stride"] = r.get("control", "stride")
    dim = values["dim"]
    for key in ("gravity",):
        if values[key] is not None and len(values[key]) != dim:
            r.fail("sim", key, f"{dim} numbers for sim.dim = {dim}")
    if values["stride"] > values["steps"]:
        r.fail("control", "stride", f"at most sim.steps = {values['steps']}")
    least = min_n_grid(values["bound"])
    if values["n_grid"] < least:
        r.fail("sim", "n_grid", f"an integer >= {least} for sim.bound = {values['bound']} (config.min_n_grid)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CFLWarning)  # refused below, in one line
            sim = SimConfig(**values)
    except ConfigError as e:
        name = str(e).split(" ", 1)[0]
        section = "control" if name == "stride" else "sim"
        raise SceneError(f"{path}: {section}.{e}") from None
    if sim.dt > sim.cfl_dt:  # repr: the shortest decimals that tell two floats apart, so dt reads > the limit
        r.fail("sim", "dt", f"at most the CFL limit dx / wave speed = {sim.cfl_dt!r} for these n_grid, E, nu "
                            "and density")

    # [scene]
    if not r.has("scene", "initial"):
        raise SceneError(f"{path}: scene.initial: missing; expected the path of the initial shape image")
    initial = r.shape("scene", "initial", r.get("scene", "initial"), dim)
    kind = r.get("loss", "kind")
    target = None
    if kind == "position":
        if r.has("scene", "target"):
            r.fail("scene", "target", "no target image with loss.kind = \"position\" (its targets are the "
                                      "initial particles moved by loss.target_scale and loss.target_offset)")
    elif not r.has("scene", "target"):
        raise SceneError(f"{path}: scene.target: missing; expected the path of the target shape image for "
                         f"loss.kind = \"{kind}\"")
    else:
        target = r.shape("scene", "target", r.get("scene", "target"), dim)
    region = r.get("scene", "region")
    if region is not None:
        lo, hi = sim.dx, 1.0 - 2.0 * sim.dx  # where a particle's 4^dim stencil fits on the grid
        names = "xyz"[:dim]
        box = f"[{', '.join(a + '0' for a in names)}, {', '.join(a + '1' for a in names)}]"
        if len(region) != 2 * dim or not all(lo <= region[a] < region[dim + a] <= hi for a in range(dim)):
            r.fail("scene", "region", f"{box} with {lo:.4g} <= x0 < x1 <= {hi:.4g} and the same for "
                                      f"{' and '.join(names[1:])} (dx to 1 - 2 dx at n_grid {sim.n_grid}"
                                      + (f", sim.dim = {dim})" if dim == 3 else ")"))

    target_shift = r.get("scene", "target_shift") or (0.0,) * dim
    if kind == "position" and r.has("scene", "target_shift"):
        r.fail("scene", "target_shift", "no target_shift with loss.kind = \"position\" (use loss.target_offset)")
    if len(target_shift) != dim:
        r.fail("scene", "target_shift", f"{dim} numbers for sim.dim = {dim}")

    # [loss]
    grids = r.get("loss", "grids") or (sim.n_grid,)
    weights = r.get("loss", "weights") or (1.0,) * len(grids)
    if len(weights) != len(grids):
        r.fail("loss", "weights", f"one weight per loss grid ({len(grids)}: loss.grids = {toml_text(list(grids))})")
    if kind not in ("ot", "color") and any(w <= 0 for w in weights):
        r.fail("loss", "weights", "a non-empty list of numbers > 0 (0 is allowed only with loss.kind = \"ot\" or "
                                  "\"color\", where a grid may carry only its loss.mass_weights or loss.ot_weights term)")
    penalty = r.get("loss", "penalty")
    if kind not in ("mass", "log_mass") and penalty != 0.0:
        r.fail("loss", "penalty", f"0 with loss.kind = \"{kind}\" (penalty grids weigh the mass losses)")
    if isinstance(penalty, str):
        if dim == 3:
            r.fail("loss", "penalty", "a number with sim.dim = 3 (0, or >= 1 on empty target nodes; a penalty image "
                                      "is 2D)")
        penalty = r.image("loss", "penalty", penalty)
    moves = {key: _per_axis(r, "loss", key, dim) for key in ("target_scale", "target_offset")}
    for key in moves:
        if kind != "position" and r.has("loss", key):
            r.fail("loss", key, f"no {key} with loss.kind = \"{kind}\" (it moves the position loss's targets)")
    for key, kinds in (("ot_blur", ("ot", "color")), ("ot_reach", ("ot",)), ("mass_weights", ("ot",)),
                       ("ot_weights", ("color",))):
        if kind not in kinds and r.has("loss", key):
            r.fail("loss", key, f"no {key} with loss.kind = \"{kind}\" (it sets the optimal-transport loss, "
                                f"loss.kind = {' or '.join(f'{chr(34)}{k}{chr(34)}' for k in kinds)})")
    second = {"ot": "mass_weights", "color": "ot_weights"}.get(kind)  # the other term's weights, one per grid
    extra = (r.get("loss", second) or ()) if second else ()
    if extra and len(extra) != len(grids):
        r.fail("loss", second, f"one weight per loss grid ({len(grids)}: loss.grids = {toml_text(list(grids))})")
    if second and any(w + e <= 0 for w, e in zip(weights, extra or (0.0,) * len(grids))):
        first = "a transport" if kind == "ot" else "a colour"
        other = "a mass" if kind == "ot" else "a transport"
        r.fail("loss", "weights", f"on every loss grid {first} weight (loss.weights) or {other} weight "
                                  f"(loss.{second}) > 0")
    mass_weights = extra if kind == "ot" else ()
    ot_weights = extra if kind == "color" else ()
    loss = LossSettings(kind=kind, grids=grids, weights=weights, penalty=penalty,
                        penalty_max=r.get("loss", "penalty_max"), **moves, ot_blur=r.get("loss", "ot_blur"),
                        ot_reach=r.get("loss", "ot_reach"), mass_weights=mass_weights, ot_weights=ot_weights)

    opt = {key: r.get("optimize", key) for key in SPEC["optimize"]}
    opt["schedule"] = opt["schedule"] or ()
    for k, stage in enumerate(opt["schedule"]):
        if not set(stage["grids"]) <= set(grids):
            r.fail("optimize", "schedule", f"stages whose grids are among loss.grids = {toml_text(list(grids))} "
                                           f"(stage {k + 1} has {toml_text(list(stage['grids']))})")
    if opt["schedule"] and opt["method"] == "positions":
        r.fail("optimize", "schedule", "no schedule with optimize.method = \"positions\" (each stage would restart "
                                       "the positions from the initial state)")
    optimize = OptimizeSettings(**opt)
    render = {key: r.get("render", key) for key in SPEC["render"]}
    if render["mode"] is None:
        render["mode"] = "color" if kind == "color" else "mass"
    elif dim == 2 and render["mode"] not in RENDER_MODES:
        r.fail("render", "mode", "one of " + ", ".join(f'"{m}"' for m in RENDER_MODES) + " with sim.dim = 2 ("
               + ", ".join(f'"{m}"' for m in MODES_3D if m not in RENDER_MODES) + ": 3D runs only)")
    if dim == 3 and render["background"] != "white":
        r.fail("render", "background", '"white" with sim.dim = 3 (the 3D preview is drawn on white; "transparent" '
                                       "is for 2D frames)")

    name = r.get("scene", "name")
    if name is None and not valid_name(path.stem):
        raise SceneError(f"{path}: scene.name: missing, and the file name {toml_text(path.stem)} is not a valid name; "
                         f"expected {NAME_RULE}: set scene.name or rename the file")
    return Scene(name=name or path.stem, path=path, initial=initial, target=target, region=region,
                 seed=r.get("scene", "seed"), target_density=r.get("scene", "target_density"),
                 target_shift=target_shift, repair=r.get("scene", "repair"), sim=sim, loss=loss,
                 optimize=optimize, render=RenderSettings(**render))


def _per_axis(r, section, key, dim):
    """A key of one number per axis (a number alone meaning the same on every axis, where allowed): its
    default or a number repeated dim times, or the list, refused unless it has dim entries."""
    value = r.get(section, key)
    raw = r.raw.get(section, {}).get(key)
    if not isinstance(raw, list):  # the default, or a number (2 entries as read)
        return (value[0],) * dim
    if len(value) != dim:
        r.fail(section, key, f"{dim} numbers for sim.dim = {dim}")
    return value
