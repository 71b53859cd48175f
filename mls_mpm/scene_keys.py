"""How each key of a scene file is read and checked, and how refusals are worded.

`SPEC` lists every section and key with its default and its reader; a reader returns the parsed value, or None
when the value has the wrong type or range, and comes with the words of what is expected. `Reader` applies
them to one file's raw TOML tables and raises SceneError with one line:
`<file>: <section.key> = <value>: expected <what>`.
"""
from __future__ import annotations

import datetime
import difflib
import json
import math
import re
from dataclasses import fields
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from .config import ARCHS, BOUNDARIES, DIMS, DTYPES, MAX_PARTICLES_PER_CELL, MAX_THREADS, SCHEDULES, SimConfig
from .errors import UserError
from .export3d import MODES_3D
from . import shapes
from .images import ImageError, check_image
from .meshes import is_mesh_path
from .optimize import METHODS

LOSS_KINDS = ("position", "mass", "log_mass", "color", "ot")
STEPS = ("normalized", "raw")
RENDER_MODES = ("mass", "color", "particles")  # 2D runs
RENDER_BACKGROUNDS = ("white", "transparent")  # 2D frames on white, or with an alpha channel (for compositing)
RENDER_SIZE_MIN = 16  # render.size and `render --size` in pixels
RENDER_SIZE_MAX = 8192
TARGET_DENSITY = ("match", "own")
MIN_LOSS_GRID = 4  # a loss grid needs at least one full 4x4 stencil
NAME_MAX = 128  # characters of scene.name, one folder name
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")  # one path component; never "." or ".."
INT64 = (-2 ** 63, 2 ** 63 - 1)  # TOML integers
SUGGEST_CUTOFF = 0.5  # difflib similarity below which no key is suggested
ELSEWHERE = 0.1  # similarity handicap of a key of another section than the one it was written in


class SceneError(UserError):
    """A scene file cannot be used; the message is one line naming the file, the key and what is expected."""


# ---------------------------------------------------------------------------------------------------------
# Readers: (read, expected); read(value) is the parsed value or None.

def _int(least, most=None):
    def read(v):
        if isinstance(v, bool) or not isinstance(v, int) or v < least or (most is not None and v > most):
            return None
        return v
    return read, f"an integer >= {least}" if most is None else f"an integer in [{least}, {most}]"


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


def _vecs(sizes, what):
    """A list of one of several lengths (the length for sim.dim is checked once dim is known)."""
    reads = [_vec(n, "")[0] for n in sizes]

    def read(v):
        return next((x for x in (r(v) for r in reads) if x is not None), None)
    return read, what


def _dim():
    return (lambda v: v if not isinstance(v, bool) and isinstance(v, int) and v in DIMS else None,
            "2 or 3 (the dimension of the domain and of every vector and matrix)")


def _str(what):
    return (lambda v: v if isinstance(v, str) and v else None, what)


NAME_RULE = (f"a name of letters, digits, '_', '.' or '-', starting with a letter or digit, at most {NAME_MAX} "
             "characters (it names the output folder)")


def valid_name(v) -> bool:
    """Whether v can name a run's output folder: one path component of the allowed characters."""
    return isinstance(v, str) and len(v) <= NAME_MAX and NAME.fullmatch(v) is not None


def _name():
    return (lambda v: v if valid_name(v) else None, NAME_RULE)


def _scale():
    axes = _vecs((2, 3), "")[0]
    num = _num(lambda x: x > 0, "")[0]

    def read(v):
        s = axes(v) if isinstance(v, list) else ((num(v),) * 2 if num(v) is not None else None)
        return s if s is not None and all(x > 0 for x in s) else None
    return read, "a number > 0 or a list [sx, sy] (3D: [sx, sy, sz]) of numbers > 0"


def _ints(least):
    def read(v):
        if not isinstance(v, list) or not v or any(isinstance(x, bool) or not isinstance(x, int) or x < least
                                                    for x in v):
            return None
        return tuple(v)
    return read, f"a non-empty list of integers >= {least}"


def _floats_nonnegative():
    num = _num(lambda x: x >= 0, "")[0]

    def read(v):
        if not isinstance(v, list) or not v or any(num(x) is None for x in v):
            return None
        return tuple(float(x) for x in v)
    return read, "a non-empty list of numbers >= 0"


def _schedule():
    grids = _ints(MIN_LOSS_GRID)[0]
    share = _num(lambda x: x > 0, "")[0]

    def read(v):
        if not isinstance(v, list) or not v:
            return None
        out = []
        for stage in v:
            if not isinstance(stage, dict) or set(stage) - {"grids", "share"} or "grids" not in stage:
                return None
            g, sh = grids(stage["grids"]), share(stage.get("share", 1.0))
            if g is None or sh is None:
                return None
            out.append({"grids": g, "share": sh})
        return tuple(out)
    return read, ("a non-empty list of stages {grids = [loss-grid resolutions], share = a number > 0 (default 1)}, "
                  "coarse grids first")


def _penalty():
    num = _num(lambda x: x == 0 or x >= 1, "")[0]

    def read(v):
        if isinstance(v, str) and v:
            return v  # an image path, resolved later
        return num(v)
    return read, "0 (no penalty grid), a number >= 1 (alpha on empty target nodes) or a grayscale image path"


_SIM = {f.name: f.default for f in fields(SimConfig)}
SHAPE_TEXTS = "a mesh path (.obj .stl .ply .off .glb), \"shape:NAME?key=value&...\" or \"extrude:IMAGE?depth=D\""

# section -> key -> (default, (reader, expected)); a default of None means optional without a value.
SPEC = {
    "scene": {
        "name": (None, _name()),
        "initial": (None, _str(f"the initial shape: an image path (2D); {SHAPE_TEXTS} (3D)")),
        "target": (None, _str(f"the target shape: an image path (2D); {SHAPE_TEXTS} (3D)")),
        "region": (None, _vecs((4, 6), "[x0, y0, x1, y1] (2D) or [x0, y0, z0, x1, y1, z1] (3D), the box the shapes "
                                       "are fitted into")),
        "seed": (0, _int(0)),
        "target_density": ("match", _choice(TARGET_DENSITY)),
        "target_shift": (None, _vecs((2, 3), "a list [dx, dy] of two numbers (domain units; 3D: [dx, dy, dz], three)")),
        "repair": (False, _bool()),
    },
    "sim": {
        "dim": (_SIM["dim"], _dim()),
        "n_grid": (_SIM["n_grid"], _int(1)),
        "steps": (_SIM["steps"], _int(1)),
        "dt": (_SIM["dt"], _num(lambda x: x > 0, "a number > 0")),
        "E": (_SIM["E"], _num(lambda x: x > 0, "a number > 0")),
        "nu": (_SIM["nu"], _num(lambda x: 0 <= x < 0.5, "a Poisson ratio in [0, 0.5)")),
        "density": (_SIM["density"], _num(lambda x: x > 0, "a number > 0")),
        "gamma": (_SIM["gamma"], _num(lambda x: x >= 0, "a number >= 0")),
        "gravity": (None, _vecs((2, 3), "a list [gx, gy] of two numbers (3D: [gx, gy, gz], three)")),
        "boundary": (_SIM["boundary"], _choice(BOUNDARIES)),
        "bound": (_SIM["bound"], _int(0)),
        "particles_per_cell": (_SIM["particles_per_cell"], _int(1, MAX_PARTICLES_PER_CELL)),
        "dtype": (_SIM["dtype"], _choice(DTYPES)),
        "arch": (_SIM["arch"], _choice(ARCHS)),
        "threads": (_SIM["threads"], _int(0, MAX_THREADS)),
        "schedule": (_SIM["schedule"], _choice(SCHEDULES)),
        "max_memory_gb": (_SIM["max_memory_gb"], _num(lambda x: x >= 0, "a number >= 0 (0: automatic)")),
    },
    "control": {
        "stride": (_SIM["stride"], _int(1)),
    },
    "loss": {
        "kind": ("mass", _choice(LOSS_KINDS)),
        "grids": (None, _ints(MIN_LOSS_GRID)),
        "weights": (None, _floats_nonnegative()),
        "penalty": (0.0, _penalty()),
        "penalty_max": (10.0, _num(lambda x: x >= 1, "a number >= 1")),
        "ot_blur": (2.0, _num(lambda x: 0.25 <= x <= 64, "a number in [0.25, 64] (cells of each loss grid)")),
        "ot_reach": (None, _num(lambda x: x > 0, "a number > 0 (domain units; leave it out for balanced transport)")),
        "mass_weights": (None, _floats_nonnegative()),
        "ot_weights": (None, _floats_nonnegative()),
        "target_scale": ([1.0, 1.0], _scale()),
        "target_offset": ([0.0, 0.0], _vecs((2, 3), "a list [dx, dy] of two numbers (3D: [dx, dy, dz], three)")),
    },
    "optimize": {
        "method": ("gd", _choice(tuple(METHODS))),
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
        "schedule": (None, _schedule()),
        "max_seconds": (0.0, _num(lambda x: x >= 0, "a number >= 0 (seconds of wall-clock time; 0: no budget)")),
    },
    "render": {
        "every": (5, _int(1)),
        "size": (512, _int(RENDER_SIZE_MIN, RENDER_SIZE_MAX)),
        "mode": (None, _choice(RENDER_MODES + tuple(m for m in MODES_3D if m not in RENDER_MODES))),
        "background": ("white", _choice(RENDER_BACKGROUNDS)),
        "gif": (True, _bool()),
        "mp4": (True, _bool()),
        "outline": (False, _bool()),
    },
}


def toml_text(v) -> str:
    """A value as TOML would write it, on one line (dates and times in RFC 3339, as TOML writes them)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_text(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_text(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (datetime.date, datetime.time)):  # datetime.datetime is a date
        return v.isoformat()
    return repr(v)


def _suggest_section(word) -> str:
    """"did you mean 'sim'?" for the closest section, or the list of sections."""
    close = difflib.get_close_matches(word, list(SPEC), n=1, cutoff=SUGGEST_CUTOFF)
    if close:
        return f"did you mean '{close[0]}'?"
    return "expected one of " + ", ".join(f"[{s}]" for s in SPEC)


def _suggest_key(section, key) -> str:
    """"did you mean 'n_grid'?" for a key of `section`, "did you mean 'control.stride'?" for one of another
    section: the key of that name in another section, else the closest key of any section (those of `section`
    preferred), else the list of the keys of `section`."""
    elsewhere = [s for s in SPEC if s != section and key in SPEC[s]]
    if elsewhere:
        return "did you mean " + " or ".join(f"'{s}.{key}'" for s in elsewhere) + "?"
    scored = [(difflib.SequenceMatcher(None, key, k).ratio() - (0.0 if s == section else ELSEWHERE),
               k if s == section else f"{s}.{k}") for s, keys in SPEC.items() for k in keys]
    score, best = max(scored, key=lambda c: c[0])  # the first of equal scores
    if score >= SUGGEST_CUTOFF:
        return f"did you mean '{best}'?"
    return "expected one of " + ", ".join(SPEC[section])


def _int64(v) -> bool:
    """Whether every integer in v lies in TOML's 64-bit range (the parser reads larger ones, TOML refuses them)."""
    if isinstance(v, list):
        return all(_int64(x) for x in v)
    if isinstance(v, dict):
        return all(_int64(x) for x in v.values())
    return not isinstance(v, int) or INT64[0] <= v <= INT64[1]


class Reader:
    """Reads one scene's raw TOML tables, remembering which keys came from --set, and words the errors."""

    def __init__(self, path, raw, from_set):
        self.path = path
        self.raw = raw
        self.from_set = from_set

    def where(self, section, key):
        v = self.raw.get(section, {}).get(key)
        origin = " (from --set)" if (section, key) in self.from_set else ""
        return f"{self.path}: {section}.{key} = {toml_text(v)}{origin}"

    def fail(self, section, key, expected):
        raise SceneError(f"{self.where(section, key)}: expected {expected}")

    def has(self, section, key):
        return key in self.raw.get(section, {})

    def get(self, section, key):
        """The parsed value of section.key, or its default."""
        default, (read, expected) = SPEC[section][key]
        if not self.has(section, key):
            return read(default) if default is not None else None
        raw = self.raw[section][key]
        value = read(raw)
        if value is None:
            self.fail(section, key, expected)
        if not _int64(raw):
            self.fail(section, key, f"{expected}, within TOML's 64-bit integers (-2^63 to 2^63 - 1)")
        return value

    def check_names(self):
        for section, table in self.raw.items():
            if not isinstance(table, dict):
                raise SceneError(f"{self.path}: {section} = {toml_text(table)}: expected a key inside a section, "
                                 f"one of {', '.join(f'[{s}]' for s in SPEC)}")
            if section not in SPEC:
                origin = " (from --set)" if any(s == section for s, _ in self.from_set) else ""
                raise SceneError(f"{self.path}: [{section}]{origin}: unknown section; {_suggest_section(section)}")
            for key in table:
                if key not in SPEC[section]:
                    raise SceneError(f"{self.where(section, key)}: unknown key in [{section}]; "
                                     f"{_suggest_key(section, key)}")

    def resolve(self, section, key, value):
        """Absolute path of a file key: relative to the scene file, or to the working directory for --set."""
        p = Path(value).expanduser()
        if not p.is_absolute():
            p = (Path.cwd() if (section, key) in self.from_set else self.path.parent) / p
        return p.resolve()

    def image(self, section, key, value):
        """Absolute path of an image key, the image checked readable (images.check_image)."""
        p = self.resolve(section, key, value)
        try:
            check_image(p)
        except ImageError as e:
            reason = str(e).split(": ", 1)[1]
            self.fail(section, key, f"an image file ({p}: {reason})")
        return p

    def shape(self, section, key, value, dim):
        """The initial or target shape: an image path in 2D; in 3D a mesh path (checked to exist: it is read
        when the scene is built), or the canonical text of a built-in shape or an extruded image (shapes.py)."""
        special = value.startswith(("shape:", "extrude:")) or is_mesh_path(value)
        if dim == 2:
            if special:
                self.fail(section, key, "an image file in a 2D scene (meshes, shape: and extrude: need sim.dim = 3)")
            return self.image(section, key, value)
        try:
            kind, body, params = shapes.parse(value)
        except shapes.ShapeError as e:
            self.fail(section, key, f"a shape ({e})")
        if kind == "shape":
            return shapes.text_of(kind, body, params)
        if kind == "extrude":
            return shapes.text_of(kind, self.image(section, key, body), params)
        p = self.resolve(section, key, body)
        if not is_mesh_path(p):
            self.fail(section, key, f"{SHAPE_TEXTS} in a 3D scene (a 2D image needs extrude:, e.g. "
                                    f"\"extrude:{value}\")")
        if not p.is_file():
            self.fail(section, key, f"a mesh file ({p}: {'no such mesh file' if not p.exists() else 'not a file'})")
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
