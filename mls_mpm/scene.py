"""Scene files: TOML data validated when loaded (STYLE 7); every key and default is listed in scenes/README.md.

A scene has the sections [scene], [sim], [control], [loss], [optimize] and [render]. `load_scene` checks every
key's type and range and refuses anything else with one line: `<file>: <section.key> = <value>: expected <what>`.
"""
from __future__ import annotations

import difflib
import json
import math
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .config import ARCHS, BOUNDARIES, DTYPES, SCHEDULES, ConfigError, SimConfig, min_n_grid
from .images import ImageError, load_image
from .errors import UserError

LOSS_KINDS = ("position", "mass", "log_mass", "color")
METHODS = ("gd", "adam", "lbfgs", "positions")
STEPS = ("normalized", "raw")
RENDER_MODES = ("mass", "color", "particles")
RENDER_SIZE_MIN = 16  # render.size and `render --size` in pixels
RENDER_SIZE_MAX = 8192
TARGET_DENSITY = ("match", "own")
MIN_LOSS_GRID = 4  # a loss grid needs at least one full 4x4 stencil


class SceneError(UserError):
    """A scene file cannot be used; the message is one line naming the file, the key and what is expected."""


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


@dataclass(frozen=True)
class RenderSettings:
    """[render]: frames and animations written by a run (thesis 7.1)."""

    every: int = 5
    size: int = 512
    mode: str = "mass"
    gif: bool = True
    outline: bool = False


@dataclass(frozen=True)
class Scene:
    """A loaded, validated scene; paths are absolute, sim holds [sim] and control.stride."""

    name: str
    path: Path
    initial: Path
    target: Path | None
    region: tuple | None
    seed: int
    target_density: str
    sim: SimConfig
    loss: LossSettings
    optimize: OptimizeSettings
    render: RenderSettings

    def to_dict(self) -> dict:
        """Every setting as plain JSON-able data, laid out like the scene file (for summary.json)."""
        sim = asdict(self.sim)
        stride = sim.pop("stride")
        loss = asdict(self.loss)
        return _plain({
            "scene": {"name": self.name, "path": self.path, "initial": self.initial, "target": self.target,
                      "region": self.region, "seed": self.seed, "target_density": self.target_density},
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


# ---------------------------------------------------------------------------------------------------------
# Key specifications: how each key is read. A reader returns the parsed value or None when the type is wrong.

def _int(least):
    return (lambda v: v if isinstance(v, int) and not isinstance(v, bool) and v >= least else None,
            f"an integer >= {least}")


def _num(ok, what):
    def read(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
            return None
        return float(v)
    return read, what


def _choice(options):
    return (lambda v: v if isinstance(v, str) and v in options else None,
            "one of " + ", ".join(f'"{o}"' for o in options))


def _bool():
    return (lambda v: v if isinstance(v, bool) else None, "true or false")


def _vec(n, what):
    num = _num(lambda x: True, "")[0]

    def read(v):
        if not isinstance(v, list) or len(v) != n or any(num(x) is None for x in v):
            return None
        return tuple(float(x) for x in v)
    return read, what


def _str(what):
    return (lambda v: v if isinstance(v, str) and v else None, what)


def _name():
    return (lambda v: v if isinstance(v, str) and re.fullmatch(r"[A-Za-z0-9_.-]+", v) else None,
            "a name of letters, digits, '_', '.' or '-' (it names the output folder)")


def _scale():
    pair = _vec(2, "")[0]
    num = _num(lambda x: x > 0, "")[0]

    def read(v):
        s = pair(v) if isinstance(v, list) else ((num(v),) * 2 if num(v) is not None else None)
        return s if s is not None and all(x > 0 for x in s) else None
    return read, "a number > 0 or a list [sx, sy] of numbers > 0"


def _ints(least):
    def read(v):
        if not isinstance(v, list) or not v or any(isinstance(x, bool) or not isinstance(x, int) or x < least
                                                    for x in v):
            return None
        return tuple(v)
    return read, f"a non-empty list of integers >= {least}"


def _floats_positive():
    num = _num(lambda x: x > 0, "")[0]

    def read(v):
        if not isinstance(v, list) or not v or any(num(x) is None for x in v):
            return None
        return tuple(float(x) for x in v)
    return read, "a non-empty list of numbers > 0"


def _penalty():
    num = _num(lambda x: x == 0 or x >= 1, "")[0]

    def read(v):
        if isinstance(v, str) and v:
            return v  # an image path, resolved later
        return num(v)
    return read, "0 (no penalty grid), a number >= 1 (alpha on empty target nodes) or a grayscale image path"


_SIM = {f.name: f.default for f in fields(SimConfig)}

# section -> key -> (default, (reader, expected)); a default of None means optional without a value.
SPEC = {
    "scene": {
        "name": (None, _name()),
        "initial": (None, _str("the path of the initial shape image")),
        "target": (None, _str("the path of the target shape image")),
        "region": (None, _vec(4, "[x0, y0, x1, y1], the box the images are fitted into")),
        "seed": (0, _int(0)),
        "target_density": ("match", _choice(TARGET_DENSITY)),
    },
    "sim": {
        "n_grid": (_SIM["n_grid"], _int(1)),
        "steps": (_SIM["steps"], _int(1)),
        "dt": (_SIM["dt"], _num(lambda x: x > 0, "a number > 0")),
        "E": (_SIM["E"], _num(lambda x: x > 0, "a number > 0")),
        "nu": (_SIM["nu"], _num(lambda x: 0 <= x < 0.5, "a Poisson ratio in [0, 0.5)")),
        "density": (_SIM["density"], _num(lambda x: x > 0, "a number > 0")),
        "gamma": (_SIM["gamma"], _num(lambda x: x >= 0, "a number >= 0")),
        "gravity": (list(_SIM["gravity"]), _vec(2, "a list [gx, gy] of two numbers")),
        "boundary": (_SIM["boundary"], _choice(BOUNDARIES)),
        "bound": (_SIM["bound"], _int(0)),
        "particles_per_cell": (_SIM["particles_per_cell"], _int(1)),
        "dtype": (_SIM["dtype"], _choice(DTYPES)),
        "arch": (_SIM["arch"], _choice(ARCHS)),
        "threads": (_SIM["threads"], _int(0)),
        "schedule": (_SIM["schedule"], _choice(SCHEDULES)),
        "max_memory_gb": (_SIM["max_memory_gb"], _num(lambda x: x >= 0, "a number >= 0 (0: automatic)")),
    },
    "control": {
        "stride": (_SIM["stride"], _int(1)),
    },
    "loss": {
        "kind": ("mass", _choice(LOSS_KINDS)),
        "grids": (None, _ints(MIN_LOSS_GRID)),
        "weights": (None, _floats_positive()),
        "penalty": (0.0, _penalty()),
        "penalty_max": (10.0, _num(lambda x: x >= 1, "a number >= 1")),
        "target_scale": ([1.0, 1.0], _scale()),
        "target_offset": ([0.0, 0.0], _vec(2, "a list [dx, dy] of two numbers")),
    },
    "optimize": {
        "method": ("gd", _choice(METHODS)),
        "iterations": (10, _int(0)),
        "step": ("normalized", _choice(STEPS)),
        "lr": (0.1, _num(lambda x: x > 0, "a number > 0")),
        "line_search": (15, _int(0)),
        "tol": (1e-3, _num(lambda x: x >= 0, "a number >= 0")),
        "rounds": (1, _int(1)),
        "carry_state": (False, _bool()),
        "clip": (0.0, _num(lambda x: x >= 0, "a number >= 0 (0: no clipping)")),
        "adam_beta1": (0.9, _num(lambda x: 0 <= x < 1, "a number in [0, 1)")),
        "adam_beta2": (0.999, _num(lambda x: 0 <= x < 1, "a number in [0, 1)")),
    },
    "render": {
        "every": (5, _int(1)),
        "size": (512, _int(16)),
        "mode": (None, _choice(RENDER_MODES)),
        "gif": (True, _bool()),
        "outline": (False, _bool()),
    },
}


def _fmt(v) -> str:
    """A value as TOML would write it, on one line."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_fmt(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _suggest(word, options) -> str:
    """"did you mean 'x'?" for the closest option, or the list of options."""
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.5)
    if close:
        return f"did you mean '{close[0]}'?"
    return "expected one of " + ", ".join(options)


class _Reader:
    """Reads one scene's raw TOML tables, remembering which keys came from --set, and words the errors."""

    def __init__(self, path, raw, from_set):
        self.path = path
        self.raw = raw
        self.from_set = from_set

    def where(self, section, key):
        v = self.raw.get(section, {}).get(key)
        origin = " (from --set)" if (section, key) in self.from_set else ""
        return f"{self.path}: {section}.{key} = {_fmt(v)}{origin}"

    def fail(self, section, key, expected):
        raise SceneError(f"{self.where(section, key)}: expected {expected}")

    def has(self, section, key):
        return key in self.raw.get(section, {})

    def get(self, section, key):
        """The parsed value of section.key, or its default."""
        default, (read, expected) = SPEC[section][key]
        if not self.has(section, key):
            return read(default) if default is not None else None
        value = read(self.raw[section][key])
        if value is None:
            self.fail(section, key, expected)
        return value

    def check_names(self):
        for section, table in self.raw.items():
            if not isinstance(table, dict):
                raise SceneError(f"{self.path}: {section} = {_fmt(table)}: expected a key inside a section, "
                                 f"one of {', '.join(f'[{s}]' for s in SPEC)}")
            if section not in SPEC:
                origin = " (from --set)" if any(s == section for s, _ in self.from_set) else ""
                raise SceneError(f"{self.path}: [{section}]{origin}: unknown section; {_suggest(section, SPEC)}")
            for key in table:
                if key not in SPEC[section]:
                    raise SceneError(f"{self.where(section, key)}: unknown key in [{section}]; "
                                     f"{_suggest(key, SPEC[section])}")

    def image(self, section, key, value):
        """Absolute path of an image key: relative to the scene file, or to the working directory for --set."""
        p = Path(value).expanduser()
        if not p.is_absolute():
            p = (Path.cwd() if (section, key) in self.from_set else self.path.parent) / p
        p = p.resolve()
        try:
            load_image(p)
        except ImageError as e:
            reason = str(e).split(": ", 1)[1]
            self.fail(section, key, f"an image file ({p}: {reason})")
        return p


def parse_override(text: str):
    """"section.key=value" -> (section, key, value); value is parsed as TOML, else kept as a bare string."""
    name, eq, value = text.partition("=")
    section, dot, key = name.strip().partition(".")
    if not eq or not dot or not section or not key or "." in key:
        raise SceneError(f"--set {text!r}: expected section.key=value, e.g. sim.steps=100")
    value = value.strip()
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return section, key.strip(), parsed


def load_scene(path, overrides=()) -> Scene:
    """Read and validate a scene file, after applying --set overrides "section.key=value"."""
    path = Path(path).expanduser().resolve()
    if not path.is_file():
        raise SceneError(f"{path}: no such scene file")
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: not valid TOML ({' '.join(str(e).split())})") from None
    from_set = set()
    for text in overrides:
        section, key, value = parse_override(text)
        table = raw.setdefault(section, {})
        if not isinstance(table, dict):
            raise SceneError(f"{path}: --set {text!r}: {section} is not a [section] table")
        table[key] = value
        from_set.add((section, key))
    r = _Reader(path, raw, from_set)
    r.check_names()

    # [sim] and [control]
    values = {key: r.get("sim", key) for key in SPEC["sim"]}
    values["stride"] = r.get("control", "stride")
    if values["stride"] > values["steps"]:
        r.fail("control", "stride", f"at most sim.steps = {values['steps']}")
    least = min_n_grid(values["bound"])
    if values["n_grid"] < least:
        r.fail("sim", "n_grid", f"an integer >= {least} (2 (bound + 2) + 2 for bound = {values['bound']})")
    try:
        sim = SimConfig(**values)
    except ConfigError as e:
        name = str(e).split(" ", 1)[0]
        section = "control" if name == "stride" else "sim"
        raise SceneError(f"{path}: {section}.{e}") from None
    if sim.dt > sim.cfl_dt:
        r.fail("sim", "dt", f"at most the CFL limit dx / wave speed = {sim.cfl_dt:.4g} for these n_grid, E, nu "
                            "and density")

    # [scene]
    if not r.has("scene", "initial"):
        raise SceneError(f"{path}: scene.initial: missing; expected the path of the initial shape image")
    initial = r.image("scene", "initial", r.get("scene", "initial"))
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
        target = r.image("scene", "target", r.get("scene", "target"))
    region = r.get("scene", "region")
    if region is not None:
        lo, hi = sim.dx, 1.0 - 2.0 * sim.dx  # where a particle's 4x4 stencil fits on the grid
        x0, y0, x1, y1 = region
        if not (lo <= x0 < x1 <= hi and lo <= y0 < y1 <= hi):
            r.fail("scene", "region", f"[x0, y0, x1, y1] with {lo:.4g} <= x0 < x1 <= {hi:.4g} and the same for y "
                                      f"(dx to 1 - 2 dx at n_grid {sim.n_grid})")

    # [loss]
    grids = r.get("loss", "grids") or (sim.n_grid,)
    weights = r.get("loss", "weights") or (1.0,) * len(grids)
    if len(weights) != len(grids):
        r.fail("loss", "weights", f"one weight per loss grid ({len(grids)}: loss.grids = {_fmt(list(grids))})")
    penalty = r.get("loss", "penalty")
    if kind not in ("mass", "log_mass") and penalty != 0.0:
        r.fail("loss", "penalty", f"0 with loss.kind = \"{kind}\" (penalty grids weigh the mass losses)")
    if isinstance(penalty, str):
        penalty = r.image("loss", "penalty", penalty)
    moves = {key: r.get("loss", key) for key in ("target_scale", "target_offset")}
    for key in moves:
        if kind != "position" and r.has("loss", key):
            r.fail("loss", key, f"no {key} with loss.kind = \"{kind}\" (it moves the position loss's targets)")
    loss = LossSettings(kind=kind, grids=grids, weights=weights, penalty=penalty,
                        penalty_max=r.get("loss", "penalty_max"), **moves)

    optimize = OptimizeSettings(**{key: r.get("optimize", key) for key in SPEC["optimize"]})
    render = {key: r.get("render", key) for key in SPEC["render"]}
    if render["mode"] is None:
        render["mode"] = "color" if kind == "color" else "mass"

    return Scene(name=r.get("scene", "name") or path.stem, path=path, initial=initial, target=target, region=region,
                 seed=r.get("scene", "seed"), target_density=r.get("scene", "target_density"), sim=sim, loss=loss,
                 optimize=optimize, render=RenderSettings(**render))
