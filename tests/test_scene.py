"""Scene files (mls_mpm/scene.py) and the problems built from them (mls_mpm/problem.py): parsing, every refusal,
the shipped scenes, target grids and metrics. No simulation runs here."""
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mls_mpm import ColorLoss, MassLoss, OTLoss, PositionLoss
from mls_mpm.images import splat_grid
from mls_mpm.memory import loss_grid_shapes
from mls_mpm.problem import (build, color_error, iou, iou_text, loss_grids, mass_error, mass_outside, occupied,
                             rest_node_mass, target_iou)
from mls_mpm.scene import SceneError, load_scene
from mls_mpm.scene_keys import SPEC, toml_text, parse_override

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted((ROOT / "scenes").glob("*.toml"))

BASE = """
[scene]
initial = "img/disk.png"
target = "img/square.png"

[sim]
n_grid = 32
steps = 20
dt = 0.005
E = 88.0
nu = 0.3
density = 40.0
gamma = 0.5
gravity = [0.0, 0.0]
particles_per_cell = 4

[control]
stride = 5
"""


@pytest.fixture
def scene_dir(tmp_path):
    """A folder with img/disk.png, img/square.png, img/blank.png, img/ramp.png and a writer of scene files."""
    img = tmp_path / "img"
    img.mkdir()
    yy, xx = np.mgrid[:32, :32] + 0.5
    disk = (xx - 16) ** 2 + (yy - 16) ** 2 < 10 ** 2
    Image.fromarray(np.where(disk, 0, 255).astype(np.uint8)).save(img / "disk.png")
    square = np.full((32, 32), 255, np.uint8)
    square[8:24, 8:24] = 0
    Image.fromarray(square).save(img / "square.png")
    Image.fromarray(np.full((32, 32), 255, np.uint8)).save(img / "blank.png")
    ramp = np.zeros((32, 32), np.uint8)
    ramp[:, 16:] = 255  # left black (alpha 1), right white (alpha penalty_max)
    Image.fromarray(ramp).save(img / "ramp.png")
    (img / "notes.png").write_text("not an image")
    return tmp_path


def write(folder, text, name="s.toml"):
    path = folder / name
    path.write_text(text)
    return path


def edit(text, section, line):
    """BASE with `line` added at the end of [section] (the section is appended when missing)."""
    head = f"[{section}]\n"
    if head in text:
        return text.replace(head, head + line + "\n")
    return text + "\n" + head + line + "\n"


# ---- parsing -----------------------------------------------------------------------------------------------

def test_defaults(scene_dir):
    s = load_scene(write(scene_dir, BASE))
    assert s.name == "s" and s.path == scene_dir / "s.toml"
    assert s.initial == scene_dir / "img" / "disk.png" and s.target == scene_dir / "img" / "square.png"
    assert s.region is None and s.seed == 0 and s.target_density == "match"
    assert (s.sim.n_grid, s.sim.steps, s.sim.stride, s.sim.E, s.sim.gravity) == (32, 20, 5, 88.0, (0.0, 0.0))
    assert s.sim.boundary == "slip" and s.sim.bound == 3 and s.sim.dtype == "f64"
    assert s.loss.kind == "mass" and s.loss.grids == (32,) and s.loss.weights == (1.0,) and s.loss.penalty == 0
    assert s.loss.penalty_max == 10.0 and s.loss.target_scale == (1.0, 1.0) and s.loss.target_offset == (0.0, 0.0)
    o = s.optimize
    assert (o.method, o.iterations, o.step, o.lr, o.line_search, o.tol, o.rounds, o.carry_state, o.clip,
            o.adam_beta1, o.adam_beta2) == ("gd", 10, "normalized", 0.1, 15, 1e-3, 1, False, 0.0, 0.9, 0.999)
    r = s.render
    assert (r.every, r.size, r.mode, r.gif, r.outline) == (5, 512, "mass", True, False)


def test_values_are_read(scene_dir):
    text = BASE.replace('[scene]\n', '[scene]\nname = "demo-1"\nregion = [0.2, 0.2, 0.8, 0.7]\nseed = 4\n'
                                     'target_density = "own"\n')
    text += """
[loss]
kind = "log_mass"
grids = [16, 64]
weights = [2, 0.5]
penalty = 5
[optimize]
method = "adam"
iterations = 0
carry_state = true
[render]
mode = "particles"
outline = true
"""
    s = load_scene(write(scene_dir, text))
    assert s.name == "demo-1" and s.region == (0.2, 0.2, 0.8, 0.7) and s.seed == 4 and s.target_density == "own"
    assert s.loss.kind == "log_mass" and s.loss.grids == (16, 64) and s.loss.weights == (2.0, 0.5)
    assert s.loss.penalty == 5.0 and isinstance(s.loss.weights[0], float)
    assert s.optimize.method == "adam" and s.optimize.iterations == 0 and s.optimize.carry_state is True
    assert s.render.mode == "particles" and s.render.outline is True


def test_color_loss_renders_color_by_default(scene_dir):
    assert load_scene(write(scene_dir, edit(BASE, "loss", 'kind = "color"'))).render.mode == "color"


def test_position_scene_and_scalar_scale(scene_dir):
    text = BASE.replace('target = "img/square.png"\n', "")
    s = load_scene(write(scene_dir, edit(text, "loss", 'kind = "position"\ntarget_scale = 1.5\n'
                                                      'target_offset = [0.0, 0.05]')))
    assert s.target is None and s.loss.target_scale == (1.5, 1.5) and s.loss.target_offset == (0.0, 0.05)


def test_ot_scene_is_read_and_builds_an_ot_loss(scene_dir):
    """kind "ot": a grid with weight 0 keeps only its eq 11 term, a grid with mass weight 0 only its transport term;
    the OTLoss holds one GridSpec per term, with ot_blur, ot_reach and the target grids build() made."""
    s = load_scene(write(scene_dir, edit(BASE, "loss", 'kind = "ot"\ngrids = [16, 32]\nweights = [1.5, 0]\n'
                                                       'mass_weights = [0, 2]\not_blur = 1.25\not_reach = 0.3')))
    ls = s.loss
    assert (ls.kind, ls.grids, ls.weights, ls.mass_weights, ls.ot_blur, ls.ot_reach) == \
        ("ot", (16, 32), (1.5, 0.0), (0.0, 2.0), 1.25, 0.3)
    p = build(s)
    assert isinstance(p.loss, OTLoss)
    assert [(g.kind, g.res, g.weight) for g in p.loss.grids] == [("ot", 16, 1.5), ("mass", 32, 2.0)]
    ot, mass = p.loss.grids
    assert (ot.blur, ot.reach) == (1.25, 0.3)
    np.testing.assert_array_equal(ot.target[..., 0], p.target_mass_grids[0])
    np.testing.assert_array_equal(mass.target[..., 0], p.target_mass_grids[1])
    assert loss_grids(ls) == loss_grid_shapes(p.loss) == [(16, 1, False), (32, 1, False)]  # the memory check's
    balanced = build(load_scene(write(scene_dir, edit(BASE, "loss", 'kind = "ot"'))))
    assert [(g.kind, g.res, g.weight, g.blur, g.reach) for g in balanced.loss.grids] == [("ot", 32, 1.0, 2.0, None)]


def test_paths_are_relative_to_the_scene_file(scene_dir, monkeypatch):
    path = write(scene_dir, BASE)
    monkeypatch.chdir(scene_dir / "img")
    assert load_scene(path).initial == scene_dir / "img" / "disk.png"


def test_to_dict_is_plain_json_laid_out_like_the_file(scene_dir):
    s = load_scene(write(scene_dir, edit(BASE, "loss", "grids = [16, 32]")))
    d = s.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert set(d) == set(SPEC)
    for section, keys in SPEC.items():
        assert set(d[section]) >= set(keys) - {"path"}, section
    assert d["scene"]["initial"] == str(scene_dir / "img" / "disk.png") and d["loss"]["grids"] == [16, 32]
    assert d["control"] == {"stride": 5} and d["sim"]["gravity"] == [0.0, 0.0] and "stride" not in d["sim"]


# ---- overrides ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, want", [
    ("sim.steps=100", ("sim", "steps", 100)),
    ("sim.dt = 0.001", ("sim", "dt", 0.001)),
    ("sim.gravity=[0, -1.5]", ("sim", "gravity", [0, -1.5])),
    ("optimize.carry_state=true", ("optimize", "carry_state", True)),
    ("sim.dtype=f32", ("sim", "dtype", "f32")),  # not TOML: a bare string
    ('sim.dtype="f32"', ("sim", "dtype", "f32")),
    ("scene.target=img/square.png", ("scene", "target", "img/square.png")),
])
def test_parse_override(text, want):
    assert parse_override(text) == want


def test_overrides_apply(scene_dir, monkeypatch):
    monkeypatch.chdir(scene_dir)
    s = load_scene(write(scene_dir, BASE), ["sim.steps=40", "control.stride=40", "optimize.method=lbfgs",
                                            "scene.initial=img/square.png", "render.gif=false"])
    assert s.sim.steps == 40 and s.sim.stride == 40 and s.optimize.method == "lbfgs" and s.render.gif is False
    assert s.initial == scene_dir / "img" / "square.png"  # --set paths: relative to the working directory


@pytest.mark.parametrize("bad", ["sim.steps", "steps=3", "=3", "sim.=3", "sim.a.b=3"])
def test_bad_override_format_refused(scene_dir, bad):
    with pytest.raises(SceneError, match=r"expected section\.key=value"):
        load_scene(write(scene_dir, BASE), [bad])


def test_override_errors_say_so(scene_dir):
    path = write(scene_dir, BASE)
    with pytest.raises(SceneError) as e:
        load_scene(path, ["sim.steps=2.5"])
    assert str(e.value) == f"{path}: sim.steps = 2.5 (from --set): expected an integer >= 1"
    with pytest.raises(SceneError, match=r"sim\.n_grd = 3 \(from --set\): unknown key in \[sim\]; "
                                         r"did you mean 'n_grid'\?"):
        load_scene(path, ["sim.n_grd=3"])
    with pytest.raises(SceneError, match=r"\[simm\] \(from --set\): unknown section; did you mean 'sim'\?"):
        load_scene(path, ["simm.steps=3"])


# ---- refusals ----------------------------------------------------------------------------------------------

REFUSALS = [
    # unknown names
    ("sim", "n_grd = 32", r"sim\.n_grd = 32: unknown key in \[sim\]; did you mean 'n_grid'\?"),
    ("optimize", "iteration = 3", r"optimize\.iteration = 3: unknown key in \[optimize\]; did you mean 'iterations'\?"),
    ("simm", "steps = 3", r"\[simm\]: unknown section; did you mean 'sim'\?"),
    ("render", "zzz = 1", r"render\.zzz = 1: unknown key in \[render\]; expected one of every, size"),
    # a key of another section: named with its section
    ("sim", "stride = 5", r"sim\.stride = 5: unknown key in \[sim\]; did you mean 'control\.stride'\?"),
    ("sim", "strid = 5", r"sim\.strid = 5: unknown key in \[sim\]; did you mean 'control\.stride'\?"),
    ("control", "steps = 5", r"control\.steps = 5: unknown key in \[control\]; did you mean 'sim\.steps'\?"),
    ("render", "method = 5", r"render\.method = 5: unknown key in \[render\]; did you mean 'optimize\.method'\?"),
    ("optimize", "kind = 5", r"optimize\.kind = 5: unknown key in \[optimize\]; did you mean 'loss\.kind'\?"),
    # types
    ("sim", "steps = 100.0", r"sim\.steps = 100\.0: expected an integer >= 1"),
    ("sim", "n_grid = true", r"sim\.n_grid = true: expected an integer >= 1"),
    ("sim", 'dt = "fast"', r'sim\.dt = "fast": expected a number > 0'),
    ("sim", "gravity = [0.0]", r"sim\.gravity = \[0\.0\]: expected a list \[gx, gy\] of two numbers"),
    ("sim", "gravity = -9.8", r"sim\.gravity = -9\.8: expected a list \[gx, gy\]"),
    ("sim", 'boundary = "sticki"', r'sim\.boundary = "sticki": expected one of "slip", "sticky"'),
    ("sim", 'dtype = "f16"', r'sim\.dtype = "f16": expected one of "f32", "f64"'),
    ("sim", 'schedule = "fast"', r'sim\.schedule = "fast": expected one of "auto", "serial", "parallel"'),
    ("scene", "seed = -1", r"scene\.seed = -1: expected an integer >= 0"),
    ("scene", 'name = "a b"', r'scene\.name = "a b": expected a name of letters'),
    ("scene", 'name = ".."', r'scene\.name = "\.\.": expected a name of letters, digits, .* starting with a letter'),
    ("scene", 'name = "."', r'scene\.name = "\.": expected a name of letters'),
    ("scene", 'name = ".hidden"', r'scene\.name = "\.hidden": expected a name of letters'),
    ("scene", 'name = "-x"', r'scene\.name = "-x": expected a name of letters'),
    ("scene", 'name = "a/b"', r'scene\.name = "a/b": expected a name of letters'),
    ("scene", 'name = "../out"', r'scene\.name = "\.\./out": expected a name of letters'),
    ("scene", 'name = ""', r'scene\.name = "": expected a name of letters'),
    ("scene", f'name = "{"a" * 129}"', r'scene\.name = "a{129}": expected a name of .* at most 128 characters'),
    # dates print as TOML writes them
    ("sim", "dt = 1979-05-27", r"sim\.dt = 1979-05-27: expected a number > 0$"),
    ("sim", "steps = 1979-05-27T07:32:00Z", r"sim\.steps = 1979-05-27T07:32:00\+00:00: expected an integer"),
    ("sim", "steps = 07:32:00.5", r"sim\.steps = 07:32:00\.500000: expected an integer"),
    ("optimize", "lr = [1979-05-27]", r"optimize\.lr = \[1979-05-27\]: expected a number > 0"),
    ("scene", 'target_density = "same"', r'scene\.target_density = "same": expected one of "match", "own"'),
    ("scene", "region = [0.2, 0.2]", r"scene\.region = \[0\.2, 0\.2\]: expected \[x0, y0, x1, y1\]"),
    ("loss", 'kind = "masss"', r'loss\.kind = "masss": expected one of "position", "mass", "log_mass", "color", "ot"$'),
    ("loss", "grids = [32.0]", r"loss\.grids = \[32\.0\]: expected a non-empty list of integers >= 4"),
    ("loss", "grids = 32", r"loss\.grids = 32: expected a non-empty list"),
    ("loss", "grids = []", r"loss\.grids = \[\]: expected a non-empty list"),
    ("loss", 'weights = ["a"]', r'loss\.weights = \["a"\]: expected a non-empty list of numbers >= 0$'),
    ("loss", 'kind = "ot"\nmass_weights = ["a"]', r'loss\.mass_weights = \["a"\]: expected a non-empty list of numbers >= 0$'),
    ("optimize", "carry_state = 1", r"optimize\.carry_state = 1: expected true or false"),
    ("optimize", 'method = "sgd"', r'optimize\.method = "sgd": expected one of "gd", "adam", "lbfgs", "positions"'),
    ("optimize", 'step = "big"', r'optimize\.step = "big": expected one of "normalized", "raw"'),
    ("render", "gif = \"yes\"", r'render\.gif = "yes": expected true or false'),
    ("render", 'mode = "density"', r'render\.mode = "density": expected one of "mass", "color", "particles"'),
    ("sim", "E = {a = 1}", r"sim\.E = \{a = 1\}: expected a number > 0"),
    # ranges
    ("sim", "steps = 0", r"sim\.steps = 0: expected an integer >= 1"),
    ("sim", "dt = -0.1", r"sim\.dt = -0\.1: expected a number > 0"),
    ("sim", "dt = nan", r"sim\.dt = nan: expected a number > 0"),
    ("sim", "dt = 0.05", r"sim\.dt = 0\.05: expected at most the CFL limit dx / wave speed = 0\.018"),
    ("sim", "E = 0", r"sim\.E = 0: expected a number > 0"),
    ("sim", "nu = 0.5", r"sim\.nu = 0\.5: expected a Poisson ratio in \[0, 0\.5\)"),
    ("sim", "density = 0", r"sim\.density = 0: expected a number > 0"),
    ("sim", "gamma = -1", r"sim\.gamma = -1: expected a number >= 0"),
    ("sim", "gamma = 300.0", r"sim\.gamma \* dt = 1\.5: expected < 1"),
    ("sim", "bound = 0\nn_grid = 5", r"sim\.n_grid = 5: expected an integer >= 6 for sim\.bound = 0"),
    ("sim", "n_grid = 11", r"sim\.n_grid = 11: expected an integer >= 12 for sim\.bound = 3 \(config\.min_n_grid\)"),
    ("sim", "particles_per_cell = 0", r"sim\.particles_per_cell = 0: expected an integer in \[1, 1024\]"),
    ("sim", "particles_per_cell = 1025", r"sim\.particles_per_cell = 1025: expected an integer in \[1, 1024\]"),
    ("sim", "particles_per_cell = 1000000000000000000000000000000",
     r"sim\.particles_per_cell = 10{30}: expected an integer in \[1, 1024\]"),
    ("sim", "threads = 1000000000000000000000000000000", r"sim\.threads = 10{30}: expected an integer in \[0, 1024\]"),
    ("sim", "steps = 1" + "0" * 400, r"sim\.steps = 10{400}: expected an integer >= 1, within TOML's 64-bit integers"),
    ("loss", "grids = [16, 9223372036854775808]", r"loss\.grids = \[16, 9223372036854775808\]: expected a non-empty "
                                                  r"list of integers >= 4, within TOML's 64-bit integers"),
    ("sim", "threads = -1", r"sim\.threads = -1: expected an integer in \[0, 1024\]"),
    ("control", "stride = 0", r"control\.stride = 0: expected an integer >= 1"),
    ("control", "stride = 21", r"control\.stride = 21: expected at most sim\.steps = 20"),
    ("scene", "region = [0.0, 0.2, 0.8, 0.8]", r"scene\.region = \[0\.0, 0\.2, 0\.8, 0\.8\]: expected \[x0, y0, x1, y1\] "
                                               r"with 0\.03125 <= x0 < x1 <= 0\.9375"),
    ("scene", "region = [0.5, 0.2, 0.4, 0.8]", r"scene\.region = .*: expected \[x0, y0, x1, y1\] with"),
    ("loss", "grids = [3]", r"loss\.grids = \[3\]: expected a non-empty list of integers >= 4"),
    ("loss", "weights = [0.0]", r'loss\.weights = \[0\.0\]: expected a non-empty list of numbers > 0 \(0 is allowed only '
                                r'with loss\.kind = "ot"'),
    ("loss", "weights = [-1.0]", r"loss\.weights = \[-1\.0\]: expected a non-empty list of numbers >= 0$"),
    ("loss", 'kind = "ot"\nweights = [1.0, -0.5]', r"loss\.weights = \[1\.0, -0\.5\]: expected a non-empty list of "
                                                  r"numbers >= 0$"),
    ("loss", "weights = [1.0, 2.0]", r"loss\.weights = \[1\.0, 2\.0\]: expected one weight per loss grid \(1: "
                                     r"loss\.grids = \[32\]\)"),
    ("loss", "penalty = 0.5", r"loss\.penalty = 0\.5: expected 0 \(no penalty grid\), a number >= 1"),
    ("loss", "penalty_max = 0.5", r"loss\.penalty_max = 0\.5: expected a number >= 1"),
    ("loss", 'kind = "ot"\not_blur = 0.2', r"loss\.ot_blur = 0\.2: expected a number in \[0\.25, 64\] \(cells of each "
                                        r"loss grid\)$"),
    ("loss", 'kind = "ot"\not_blur = 65', r"loss\.ot_blur = 65: expected a number in \[0\.25, 64\]"),
    ("loss", 'kind = "ot"\not_blur = nan', r"loss\.ot_blur = nan: expected a number in \[0\.25, 64\]"),
    ("loss", 'kind = "ot"\not_reach = 0', r"loss\.ot_reach = 0: expected a number > 0 \(domain units; leave it out "
                                       r"for balanced transport\)$"),
    ("loss", 'kind = "ot"\not_reach = -0.3', r"loss\.ot_reach = -0\.3: expected a number > 0"),
    ("loss", 'kind = "ot"\nmass_weights = [1.0, 1.0]', r"loss\.mass_weights = \[1\.0, 1\.0\]: expected one weight per "
                                                     r"loss grid \(1: loss\.grids = \[32\]\)$"),
    ("loss", 'kind = "ot"\ngrids = [16, 32]\nmass_weights = [1.0]',
     r"loss\.mass_weights = \[1\.0\]: expected one weight per loss grid \(2: loss\.grids = \[16, 32\]\)$"),
    ("loss", "target_scale = [1.0, -1.0]", r"loss\.target_scale = \[1\.0, -1\.0\]: expected a number > 0 or a list"),
    ("optimize", "iterations = -1", r"optimize\.iterations = -1: expected an integer >= 0"),
    ("optimize", "lr = 0", r"optimize\.lr = 0: expected a number > 0"),
    ("optimize", "rounds = 0", r"optimize\.rounds = 0: expected an integer >= 1"),
    ("optimize", "adam_beta2 = 1.0", r"optimize\.adam_beta2 = 1\.0: expected a number in \[0, 1\)"),
    ("render", "every = 0", r"render\.every = 0: expected an integer >= 1"),
    ("render", "size = 8", r"render\.size = 8: expected an integer in \[16, 8192\]"),
    ("render", "size = 8193", r"render\.size = 8193: expected an integer in \[16, 8192\]"),
    ("render", "size = 100000", r"render\.size = 100000: expected an integer in \[16, 8192\]"),
    # images
    ("scene", 'initial = "img/missing.png"', r'scene\.initial = "img/missing\.png": expected an image file '
                                             r'\(.*missing\.png: no such image file\)'),
    ("scene", 'target = "img/notes.png"', r'scene\.target = "img/notes\.png": expected an image file \(.*not an image'),
    ("loss", 'penalty = "img/none.png"', r'loss\.penalty = "img/none\.png": expected an image file'),
    # combinations
    ("loss", 'kind = "color"\npenalty = 10', r'loss\.penalty = 10: expected 0 with loss\.kind = "color"'),
    ("loss", "target_offset = [0.0, 0.1]", r'loss\.target_offset = \[0\.0, 0\.1\]: expected no target_offset with '
                                           r'loss\.kind = "mass"'),
    ("loss", 'kind = "position"', r'scene\.target = "img/square\.png": expected no target image with '
                                  r'loss\.kind = "position"'),
    ("loss", "ot_blur = 2.0", r'loss\.ot_blur = 2\.0: expected no ot_blur with loss\.kind = "mass" \(it sets the '
                              r'optimal-transport loss, loss\.kind = "ot" or "color"\)$'),
    ("loss", "ot_weights = [1.0]", r'loss\.ot_weights = \[1\.0\]: expected no ot_weights with loss\.kind = "mass" '
                                   r'\(it sets the optimal-transport loss, loss\.kind = "color"\)$'),
    ("loss", 'kind = "color"\nweights = [0.0]\not_weights = [0.0]',
     r'loss\.weights = \[0\.0\]: expected on every loss grid a colour weight \(loss\.weights\) or a transport '
     r'weight \(loss\.ot_weights\) > 0'),
    ("loss", 'kind = "color"\not_weights = [1.0, 2.0]', r'loss\.ot_weights = \[1\.0, 2\.0\]: expected one weight per '
                                                       r'loss grid \(1'),
    ("loss", "ot_reach = 0.3", r'loss\.ot_reach = 0\.3: expected no ot_reach with loss\.kind = "mass"'),
    ("loss", 'kind = "color"\nmass_weights = [1.0]', r'loss\.mass_weights = \[1\.0\]: expected no mass_weights with '
                                                    r'loss\.kind = "color"'),
    ("loss", 'kind = "ot"\nweights = [0.0]', r"loss\.weights = \[0\.0\]: expected on every loss grid a transport weight "
                                          r"\(loss\.weights\) or a mass weight \(loss\.mass_weights\) > 0$"),
    ("loss", 'kind = "ot"\ngrids = [16, 32]\nweights = [1.0, 0.0]\nmass_weights = [0.0, 0.0]',
     r"loss\.weights = \[1\.0, 0\.0\]: expected on every loss grid a transport weight"),
    ("loss", 'kind = "ot"\npenalty = 10', r'loss\.penalty = 10: expected 0 with loss\.kind = "ot"'),
]


@pytest.mark.parametrize("section, line, pattern", REFUSALS, ids=[f"{s}:{l.split(chr(10))[-1]}" for s, l, _ in REFUSALS])
def test_refusals(scene_dir, section, line, pattern):
    """Each refusal is one SceneError line: `<file>: <section.key> = <value>: expected <what>`."""
    text = BASE
    for key in re.findall(r"^(\w+) =", line, re.M):  # replace a key BASE already sets
        text = re.sub(rf"^{key} = .*\n", "", text, flags=re.M) if f"[{section}]" in text else text
    path = write(scene_dir, edit(text, section, line))
    with pytest.raises(SceneError) as e:
        load_scene(path)
    message = str(e.value)
    assert "\n" not in message and message.startswith(f"{path}: ")
    assert re.search(pattern, message), message


def test_a_key_written_in_another_section_is_named_with_its_own(scene_dir):
    """Every key of every section, written into each other section, is refused with "did you mean <its
    section>.<key>?" (a name of two sections, `schedule` of [sim] and [optimize], names both)."""
    for section, keys in SPEC.items():
        for key in keys:
            for wrong in SPEC:
                if wrong == section or key in SPEC[wrong]:
                    continue
                homes = " or ".join(f"'{s}.{key}'" for s in SPEC if s != wrong and key in SPEC[s])
                path = write(scene_dir, BASE + f"\n[{wrong}]\n{key} = 1\n" if f"[{wrong}]" not in BASE
                             else BASE.replace(f"[{wrong}]\n", f"[{wrong}]\n{key} = 1\n"))
                with pytest.raises(SceneError) as e:
                    load_scene(path)
                assert str(e.value) == (f"{path}: {wrong}.{key} = 1: unknown key in [{wrong}]; "
                                        f"did you mean {homes}?")


def test_byte_order_mark_is_allowed(scene_dir):
    path = scene_dir / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + BASE.encode())
    assert load_scene(path).sim.n_grid == 32


def test_cfl_refusal_is_one_line_with_digits_that_tell_dt_above_the_limit(scene_dir):
    """dt one ulp above the limit: no CFLWarning besides the refusal, and the printed numbers, read back,
    show dt > limit."""
    limit = load_scene(write(scene_dir, BASE)).sim.cfl_dt
    dt = float(np.nextafter(limit, np.inf))
    path = write(scene_dir, re.sub(r"^dt = .*$", f"dt = {dt!r}", BASE, flags=re.M))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(SceneError) as e:
            load_scene(path)
    assert not caught, [str(w.message) for w in caught]
    m = re.fullmatch(rf"{re.escape(str(path))}: sim\.dt = (\S+): expected at most the CFL limit dx / wave speed = "
                     r"(\S+) for these n_grid, E, nu and density", str(e.value))
    assert m, str(e.value)
    assert float(m.group(1)) == dt and float(m.group(2)) == limit and float(m.group(1)) > float(m.group(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # at the limit itself: loads, and warns nothing
        assert load_scene(write(scene_dir, re.sub(r"^dt = .*$", f"dt = {limit!r}", BASE, flags=re.M))).sim.dt == limit


@pytest.mark.parametrize("stem", ["..", ".", "my scene", ".hidden"])
def test_a_file_name_that_is_not_a_name_needs_scene_name(scene_dir, stem):
    """Without scene.name the file name names the output folder, so it must be a valid name too."""
    path = write(scene_dir, BASE, name=f"{stem}.toml")
    with pytest.raises(SceneError) as e:
        load_scene(path)
    assert str(e.value).startswith(f"{path}: scene.name: missing, and the file name {json.dumps(stem)} is not a "
                                   "valid name; expected a name of letters")
    assert load_scene(path, ['scene.name="ok"']).name == "ok"


def test_directory_or_device_as_scene_file(scene_dir):
    with pytest.raises(SceneError) as e:
        load_scene(scene_dir)
    assert str(e.value) == f"{scene_dir}: is a directory; expected a scene file (TOML)"
    with pytest.raises(SceneError) as e:
        load_scene("/dev/zero")
    assert str(e.value) == "/dev/zero: is not a regular file (a device, pipe or socket); expected a scene file (TOML)"


def test_methods_are_the_optimizers():
    from mls_mpm.optimize import METHODS
    assert SPEC["optimize"]["method"][1][1] == "one of " + ", ".join(f'"{m}"' for m in METHODS)


def test_missing_initial_and_target(scene_dir):
    with pytest.raises(SceneError, match=r"scene\.initial: missing; expected the path of the initial shape image"):
        load_scene(write(scene_dir, BASE.replace('initial = "img/disk.png"\n', "")))
    with pytest.raises(SceneError, match=r'scene\.target: missing; expected .* for loss\.kind = "mass"'):
        load_scene(write(scene_dir, BASE.replace('target = "img/square.png"\n', "")))


def test_not_toml_and_missing_file(scene_dir):
    with pytest.raises(SceneError, match=r"s\.toml: not valid TOML \(") as e:
        load_scene(write(scene_dir, BASE + "\n[sim\n"))
    assert "\n" not in str(e.value)
    with pytest.raises(SceneError, match=r"nope\.toml: no such scene file"):
        load_scene(scene_dir / "nope.toml")


def test_top_level_value_refused(scene_dir):
    with pytest.raises(SceneError, match=r"s\.toml: steps = 3: expected a key inside a section, one of \[scene\], "
                                         r"\[sim\], \[control\], \[loss\], \[optimize\], \[render\]$"):
        load_scene(write(scene_dir, "steps = 3\n" + BASE))


def test_blank_image_refused_when_built(scene_dir):
    s = load_scene(write(scene_dir, BASE.replace("img/square.png", "img/blank.png")))
    with pytest.raises(SceneError, match=r'scene\.target = ".*blank\.png": expected an image with material'):
        build(s)


def test_position_targets_leaving_the_domain_refused(scene_dir):
    text = edit(BASE.replace('target = "img/square.png"\n', ""), "loss", 'kind = "position"\ntarget_offset = [0.0, 0.6]')
    with pytest.raises(SceneError, match=r"loss\.target_scale = \[1\.0, 1\.0\], loss\.target_offset = \[0\.0, 0\.6\]: "
                                         r"expected target positions inside"):
        build(load_scene(write(scene_dir, text)))


# ---- shipped scenes and the README -------------------------------------------------------------------------

def test_scenes_are_shipped():
    names = {p.stem for p in SHIPPED}
    assert {"circle_expand", "circle_jump", "genus2_to_genus4", "genus1_to_genus4", "genus2_to_genus0",
            "genus4_to_star", "genus4_to_star_converged", "genus4_to_star_penalty", "heart_break", "color_half_half",
            "color_swap", "resolution_128", "resolution_64", "resolution_32", "circle_to_star_multi",
            "circle_to_star_fine", "circle_to_torus"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scene_loads_and_builds(path):
    s = load_scene(path)
    p = build(s)
    N = len(p.x0)
    assert N > 500 and p.colors.shape == (N, 3) and s.sim.dt <= s.sim.cfl_dt
    assert p.res == max(s.loss.grids) and len(p.target_mass_grids) == len(s.loss.grids)
    for grid, res in zip(p.target_mass_grids, s.loss.grids):
        assert grid.shape == (res,) * s.sim.dim  # the *_3d scenes: (res, res, res)
        assert grid.sum() == pytest.approx(N * s.sim.m_p, rel=1e-9)  # "match", and every shape is well inside
    if s.loss.kind == "position":
        assert isinstance(p.loss, PositionLoss) and p.target_x.shape == (N, s.sim.dim)
    else:
        assert isinstance(p.loss, {"color": ColorLoss, "ot": OTLoss}.get(s.loss.kind, MassLoss))
    json.dumps(s.to_dict())


def test_circle_to_torus_is_the_thesis_program_example():
    s = load_scene(ROOT / "scenes" / "circle_to_torus.toml")
    p = build(s)
    assert (s.sim.n_grid, s.sim.steps, s.sim.stride, s.sim.particles_per_cell) == (32, 300, 10, 16)
    assert abs(len(p.x0) - 1250) < 60


def test_every_sim_config_field_is_a_key():
    from dataclasses import fields
    from mls_mpm import SimConfig
    assert {f.name for f in fields(SimConfig)} == set(SPEC["sim"]) | {"stride"}


def test_readme_documents_every_key_and_default():
    readme = (ROOT / "scenes" / "README.md").read_text()
    for section, keys in SPEC.items():
        table = readme.split(f"### [{section}]", 1)[1].split("###", 1)[0]
        for key, (default, _) in keys.items():
            row = re.search(rf"^\| `{key}` \|([^|]*)\|", table, re.M)
            assert row, f"[{section}] {key} missing from scenes/README.md"
            if default is not None:
                assert f"`{toml_text(default)}`" in row.group(1), f"[{section}] {key}: default {toml_text(default)}"
    for path in SHIPPED:
        assert f"mls-mpm run scenes/{path.name}" in readme, path.name


# ---- problems ----------------------------------------------------------------------------------------------

def test_mass_targets_match_the_body(scene_dir):
    """target_density "match": target total mass = body mass; "own": m_p per target particle."""
    s = load_scene(write(scene_dir, edit(BASE, "loss", "grids = [16, 64]")))
    p = build(s)
    N, M = len(p.x0), len(p.target_points)
    assert N != M
    for g in p.target_mass_grids:
        assert g.sum() == pytest.approx(N * s.sim.m_p, rel=1e-12)
    np.testing.assert_allclose(p.loss.grids[1].target[..., 0], p.target_mass_grids[1])
    assert p.alpha is None and p.loss.grids[0].alpha is None and p.target_x is None
    own = build(load_scene(write(scene_dir, BASE.replace("[scene]\n", '[scene]\ntarget_density = "own"\n'))))
    assert own.target_mass_grids[0].sum() == pytest.approx(M * s.sim.m_p, rel=1e-12)


def test_rest_node_mass_and_metrics(scene_dir):
    s = load_scene(write(scene_dir, BASE))
    p = build(s)
    rest = rest_node_mass(s.sim, 32)
    assert rest == pytest.approx(s.sim.m_p * s.sim.particles_per_cell)
    body = splat_grid(p.x0, s.sim.m_p, 32)
    assert np.median(body[body > 0.9 * body.max()]) == pytest.approx(rest, rel=0.1)  # interior nodes
    assert iou(occupied(body, rest), occupied(body, rest)) == 1.0
    t = p.target_mass_grids[0]
    assert 0.3 < iou(occupied(body, rest), occupied(t, rest)) < 0.9
    assert mass_outside(t, t) == pytest.approx(0.0, abs=1e-6) and 0.0 < mass_outside(body, t) < 0.5


def test_metrics_on_small_grids():
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    a[:2] = True
    b[1:3] = True
    assert iou(a, b) == pytest.approx(4 / 12) and iou(a & False, b & False) == 1.0
    mass = np.array([[1.0, 3.0], [0.0, 0.0]])
    target = np.array([[2.0, 0.0], [1.0, 0.0]])
    assert mass_outside(mass, target) == pytest.approx(0.75)
    assert occupied(mass, 10.0, frac=0.2).tolist() == [[False, True], [False, False]]


def test_target_iou_is_none_where_no_target_node_is_occupied():
    """A run's iou compares occupied nodes (above 0.1 of the rest node mass); a target whose mass lies below that
    everywhere (a body's mass spread over a much larger area) has nothing to compare with: None, printed "n/a",
    not the 1.0 that two empty grids give (an empty body would read perfect)."""
    rest = 10.0
    mass = np.array([[0.5, 3.0], [0.0, 0.0]])  # one node occupied
    target = np.array([[2.0, 2.0], [0.5, 0.0]])  # two
    assert target_iou(mass, target, rest) == pytest.approx(0.5) == iou(occupied(mass, rest), occupied(target, rest))
    thin = np.full((2, 2), 0.9)  # every node below 0.1 * rest
    assert target_iou(mass, thin, rest) is None and target_iou(0.0 * mass, thin, rest) is None
    assert iou_text(None).startswith("n/a (no target node holds 0.1 of the rest node mass")
    assert iou_text(0.5) == "0.500"


def test_mass_error_and_color_error_on_small_grids():
    """mass_error = 1/2 sum |m - m_u| / sum m_u: 0 for the same grid, 1 for disjoint grids of equal mass, the
    moved fraction for a half overlap; color_error is the largest channel's."""
    a = np.zeros((4, 4))
    b = np.zeros((4, 4))
    a[:2] = 1.0
    b[2:] = 1.0
    half = np.zeros((4, 4))
    half[1:3] = 1.0  # shares row 1 with a: half of a's mass is in place
    assert mass_error(a, a) == 0.0
    assert mass_error(a, b) == pytest.approx(1.0, rel=1e-15) and mass_error(b, a) == pytest.approx(1.0, rel=1e-15)
    assert mass_error(half, a) == pytest.approx(0.5, rel=1e-15)
    assert mass_error(2 * a, a) == pytest.approx(0.5, rel=1e-15)  # not normalised: extra mass counts
    assert mass_error(a, np.zeros((4, 4))) == 0.0  # an empty target: no error defined, reported as 0
    ca = np.stack([a, a, a], axis=-1)
    cb = np.stack([a, half, b], axis=-1)  # channel errors 0, 0.5, 1
    assert color_error(ca, ca) == 0.0
    assert color_error(cb, ca) == pytest.approx(1.0, rel=1e-15)
    assert color_error(cb[..., [0, 1, 0]], ca) == pytest.approx(0.5, rel=1e-15)


def test_penalty_number_sets_alpha_on_empty_target_nodes(scene_dir):
    p = build(load_scene(write(scene_dir, edit(BASE, "loss", "penalty = 10"))))
    alpha, target = p.alpha[0], p.target_mass_grids[0]
    assert set(np.unique(alpha)) == {1.0, 10.0}
    assert np.all(alpha[target == 0] == 10.0) and np.all(alpha[target > 1e-3 * target.max()] == 1.0)
    np.testing.assert_array_equal(p.loss.grids[0].alpha, alpha)


def test_penalty_image_black_is_one_white_is_max(scene_dir):
    s = load_scene(write(scene_dir, edit(BASE, "loss", 'penalty = "img/ramp.png"\npenalty_max = 4.0\ngrids = [32]')))
    assert s.loss.penalty == scene_dir / "img" / "ramp.png"
    alpha = build(s).alpha[0]
    assert alpha[8, 16] == 1.0 and alpha[24, 16] == 4.0  # left of the image: black; right: white
    assert set(np.unique(alpha)) == {1.0, 4.0}


def test_position_targets(scene_dir):
    text = edit(BASE.replace('target = "img/square.png"\n', ""), "loss",
                'kind = "position"\ntarget_scale = [1.5, 0.5]\ntarget_offset = [0.05, -0.1]')
    s = load_scene(write(scene_dir, text))
    p = build(s)
    c = p.x0.mean(axis=0)
    np.testing.assert_allclose(p.target_x, c + [1.5, 0.5] * (p.x0 - c) + [0.05, -0.1])
    np.testing.assert_array_equal(p.loss.target, p.target_x)
    assert p.target_mass_grids[0].sum() == pytest.approx(len(p.x0) * s.sim.m_p)


def test_color_targets_are_color_mass(scene_dir):
    red = np.zeros((32, 32, 3), np.uint8) + 255
    red[6:26, 6:26] = (255, 0, 0)
    Image.fromarray(red).save(scene_dir / "img" / "red.png")
    text = edit(BASE.replace("img/square.png", "img/red.png"), "loss", 'kind = "color"\ngrids = [16, 32]')
    s = load_scene(write(scene_dir, text))
    p = build(s)
    assert isinstance(p.loss, ColorLoss) and np.all(p.colors == 0.0)  # the black disk
    for spec, mass in zip(p.loss.grids, p.target_mass_grids):
        np.testing.assert_allclose(spec.target[..., 0], mass, atol=1e-15)  # red = mass
        assert np.all(spec.target[..., 1:] == 0.0)
    assert np.all(p.target_colors == [1.0, 0.0, 0.0])
