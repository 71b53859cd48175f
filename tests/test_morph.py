"""`mls-mpm morph INITIAL TARGET` (mls_mpm/morph.py, cli.cmd_morph): the travel distance of the transport plan,
the colour regions of an image, the scene chosen from two images (valid, steps within bounds and on the control
stride, more steps for a farther target, the loss kind of the images, --set winning, a coarser grid for --quality
fast), its one-line refusals, and a tiny run whose DIR/scene.toml reproduces it with `mls-mpm run`.

The tests check relations between choices through morph's constants (SPEED, SETTLE, the qualities), not their
values, which the quality benchmark tunes. Runs: --quality fast (32 x 32 grid), sim.steps = 20, 2 L-BFGS iterations, --seconds 600 so
that the iteration count, not a slow first compile, ends them.
"""
import json
from pathlib import Path

import numpy as np
import pytest
import taichi as ti
from PIL import Image

from conftest import blob
from mls_mpm import SimConfig, morph, runtime
from mls_mpm.cli import main
from mls_mpm.images import load_image
from mls_mpm.scene import load_scene
from mls_mpm.schedule import BUDGET_REASON

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "scenes" / "images"


def tiny_run(seconds=600, iterations=2):
    """Options of a tiny morph: fast quality, 20 steps, `iterations` L-BFGS iterations, a budget of `seconds`."""
    return ["--quality", "fast", "--no-render", "--quiet", "--seconds", str(seconds), "--set", "sim.steps=20",
            "--set", f"optimize.iterations={iterations}"]


def disk_image(path, center, radius=8, size=64, color=(0, 0, 0)):
    """A disk of `color` on white, in a size x size PNG; center in pixels (x right, y down)."""
    yy, xx = np.mgrid[:size, :size] + 0.5
    inside = (xx - center[0]) ** 2 + (yy - center[1]) ** 2 < radius ** 2
    rgb = np.full((size, size, 3), 255, np.uint8)
    rgb[inside] = color
    Image.fromarray(rgb).save(path)
    return path


def scene_of(choice, tmp_path):
    """The chosen text, loaded the way cmd_morph loads it (from a file)."""
    path = tmp_path / "chosen.toml"
    path.write_text(choice.text)
    return load_scene(path)


# ---------------------------------------------------------------------------------------------------------
# travel_distance and color_regions

def test_travel_distance_of_a_set_to_itself_is_zero():
    x = blob(n_grid=32, radius=0.15)
    assert len(x) <= morph.PLAN_SAMPLES  # the whole set: the plan is the identity
    assert morph.travel_distance(x, x.copy()) == 0.0


@pytest.mark.parametrize("n_grid, shift", [(32, (0.2, 0.0)), (32, (0.1, -0.15)), (64, (0.15, 0.1)), (64, (0.0, 0.0)),
                                           (96, (-0.1, 0.05))])
def test_travel_distance_of_a_shifted_disk_is_the_shift(n_grid, shift):
    """The optimal plan of a translated set is the translation: every particle travels |d|. On the 64 grid (~2000
    particles and more) the plan is made between subsamples of PLAN_SAMPLES less the plan's floor between two
    subsamples of one set: within two particle spacings of |d| (one on the whole set)."""
    x = blob(n_grid=n_grid, center=(0.4, 0.45), radius=0.2)
    spacing = 1.0 / n_grid / 2  # 4 particles per cell
    d = float(np.hypot(*shift))
    got = morph.travel_distance(x, x + np.asarray(shift))
    assert abs(got - d) <= (spacing if len(x) <= morph.PLAN_SAMPLES else 2 * spacing), (got, d)
    assert (len(x) > morph.PLAN_SAMPLES) == (n_grid >= 64)


def test_color_regions(tmp_path):
    black = load_image(disk_image(tmp_path / "black.png", (32, 32), radius=12))
    assert morph.color_regions(black) == 1
    assert morph.color_regions(load_image(IMAGES / "circle.png")) == 1
    for name in ("color_halves.png", "color_halves_target.png"):  # a red and a blue half
        assert morph.color_regions(load_image(IMAGES / name)) == 2, name
    # three colours, one of them a speck below COLOR_SHARE of the material: two regions
    rgb = np.full((64, 64, 3), 255, np.uint8)
    rgb[10:40, 10:30] = (255, 0, 0)
    rgb[10:40, 30:50] = (0, 0, 255)
    rgb[41, 10] = (0, 255, 0)
    Image.fromarray(rgb).save(tmp_path / "three.png")
    assert morph.color_regions(load_image(tmp_path / "three.png")) == 2


# ---------------------------------------------------------------------------------------------------------
# choose

SHIPPED_PAIRS = [("circle_small.png", "torus.png"), ("genus2.png", "genus4.png"), ("heart.png", "star.png"),
                 ("color_halves.png", "color_halves_target.png")]


@pytest.mark.parametrize("quality", ["fast", "default"])
@pytest.mark.parametrize("initial, target", SHIPPED_PAIRS)
def test_the_chosen_scene_loads_with_steps_in_bounds(tmp_path, initial, target, quality):
    choice = morph.choose(IMAGES / initial, IMAGES / target, quality)
    scene = scene_of(choice, tmp_path)
    steps = scene.sim.steps
    assert morph.MIN_STEPS <= steps <= morph.MAX_STEPS and steps % morph.STRIDE == 0
    assert scene.sim.stride == morph.STRIDE
    assert steps == choice.steps and scene.name == choice.name
    assert scene.sim.n_grid == morph.QUALITIES[quality].n_grid
    assert scene.optimize.method == "lbfgs" and scene.optimize.iterations == morph.QUALITIES[quality].iterations
    assert scene.optimize.max_seconds == morph.QUALITIES[quality].max_seconds
    assert scene.optimize.rounds == morph.QUALITIES[quality].rounds == {"fast": 1, "default": 3, "best": 2}[quality]
    assert (f"{scene.optimize.rounds} rounds" in choice.line(quality)) == (quality != "fast")
    # the stages: the coarse grid first, then every grid; colour scenes: both from the start (no schedule)
    grids = scene.loss.grids
    stages = [s["grids"] for s in scene.optimize.schedule]
    assert stages == ([] if scene.loss.kind == "color" else [(min(grids),), tuple(grids)])
    assert scene.initial == (IMAGES / initial).resolve() and scene.target == (IMAGES / target).resolve()


def test_steps_cover_the_travel_at_the_peak_speed():
    """Steps are at least the travel's 2 d / speed (accelerate, brake), unless MAX_STEPS caps them."""
    for initial, target in SHIPPED_PAIRS[:3]:
        choice = morph.choose(IMAGES / initial, IMAGES / target, "fast")
        dx = 1.0 / morph.QUALITIES["fast"].n_grid
        need = 2.0 * choice.distance / (morph.SPEED * dx)
        assert choice.steps >= min(need, morph.MAX_STEPS)
        assert abs(choice.speed - morph.SPEED * dx / morph.DT) <= 1e-12 * choice.speed


def test_a_farther_target_gets_at_least_as_many_steps(tmp_path):
    """With the target kept where its image puts it (--keep-position); by default it is moved onto the body's
    centre of mass, and the same translated disks then need no travel at all."""
    a = disk_image(tmp_path / "a.png", (20, 32))
    targets = [disk_image(tmp_path / f"b{dx}.png", (20 + dx, 32)) for dx in (0, 8, 16, 32)]
    chosen = [morph.choose(a, b, "default", keep_position=True) for b in targets]  # 64^2: 0.31 of travel needs
    centred = [morph.choose(a, b, "default") for b in targets]  # more than MIN_STEPS at SPEED cells per step
    spacing = 1.0 / morph.QUALITIES["default"].n_grid / 2  # 4 particles per cell; subsampled plans: 2 spacings
    assert all(c.distance < 2 * spacing and c.steps == morph.MIN_STEPS for c in centred), [c.distance for c in centred]
    assert all(abs(c.shift[0]) > 0.1 for c in centred[2:]) and all(abs(c.shift[1]) < 0.01 for c in centred)
    distances = [c.distance for c in chosen]
    steps = [c.steps for c in chosen]
    assert distances[0] < 1e-12 and all(b > a for a, b in zip(distances, distances[1:])), distances
    assert all(b >= a for a, b in zip(steps, steps[1:])), steps
    assert steps[-1] > steps[0], steps  # 32 of 64 pixels (0.31 of the domain, fitted) is beyond what MIN_STEPS covers


def test_the_loss_follows_the_images_and_the_loss_option(tmp_path):
    color = (IMAGES / "color_halves.png", IMAGES / "color_halves_target.png")
    assert scene_of(morph.choose(*color, "fast"), tmp_path).loss.kind == "color"
    assert scene_of(morph.choose(*color, "fast", loss="color"), tmp_path).loss.kind == "color"
    mass = scene_of(morph.choose(*color, "fast", loss="mass"), tmp_path)
    assert mass.loss.kind == "ot"
    # OT on the coarse grid alone, eq 11 on the fine grid alone
    assert mass.loss.weights[1] == 0.0 and mass.loss.mass_weights[0] == 0.0
    assert mass.loss.weights[0] > 0 and mass.loss.mass_weights[1] > 0
    # one colour region in one image: the mass loss under auto
    mixed = morph.choose(IMAGES / "circle.png", IMAGES / "color_halves_target.png", "fast")
    assert scene_of(mixed, tmp_path).loss.kind == "ot"
    plain = morph.choose(IMAGES / "circle_small.png", IMAGES / "torus.png", "fast", loss="color")
    assert scene_of(plain, tmp_path).loss.kind == "color"


def test_set_values_land_in_the_text_and_win(tmp_path):
    pair = (IMAGES / "circle_small.png", IMAGES / "torus.png")
    choice = morph.choose(*pair, "fast", sets=["sim.steps=130", "optimize.iterations=7", "optimize.max_seconds=9",
                                               "render.size=96", "scene.name=mine"])
    assert "steps = 130" in choice.text and "iterations = 7" in choice.text and "size = 96" in choice.text
    scene = scene_of(choice, tmp_path)
    assert scene.sim.steps == 130 and scene.optimize.iterations == 7 and scene.optimize.max_seconds == 9.0
    assert scene.render.size == 96
    assert scene.name == "mine" and choice.name == "mine"
    # --seconds sets the budget; a --set of it wins
    assert scene_of(morph.choose(*pair, "fast", seconds=3.0), tmp_path).optimize.max_seconds == 3.0
    # the grid set by --set is the grid the choices are made for: the loss grids follow it
    fine = scene_of(morph.choose(*pair, "fast", sets=["sim.n_grid=48"]), tmp_path)
    assert fine.sim.n_grid == 48 and max(fine.loss.grids) == 48 and min(fine.loss.grids) < 48


def test_fast_is_coarser_than_default(tmp_path):
    pair = (IMAGES / "genus2.png", IMAGES / "genus4.png")
    fast = scene_of(morph.choose(*pair, "fast"), tmp_path)
    default = scene_of(morph.choose(*pair, "default"), tmp_path)
    assert fast.sim.n_grid < default.sim.n_grid
    assert max(fast.loss.grids) < max(default.loss.grids)
    assert fast.optimize.iterations <= default.optimize.iterations


# ---------------------------------------------------------------------------------------------------------
# the command line

def one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    err = [line for line in err if not line.startswith("[")]  # Taichi's own log lines, if any
    assert len(err) == 1, err
    assert err[0].startswith("mls-mpm: error:"), err[0]
    return err[0]


@pytest.mark.parametrize("case", ["missing", "not_an_image", "all_white", "missing_target", "quality"])
def test_bad_input_is_one_line_and_creates_nothing(tmp_path, capsys, case):
    good = str(IMAGES / "circle_small.png")
    (tmp_path / "notes.png").write_text("not an image")
    Image.fromarray(np.full((32, 32), 255, np.uint8)).save(tmp_path / "white.png")
    args = {"missing": [str(tmp_path / "none.png"), good],
            "not_an_image": [str(tmp_path / "notes.png"), good],
            "all_white": [str(tmp_path / "white.png"), good],
            "missing_target": [good, str(tmp_path / "none.png")],
            "quality": [good, good, "--quality", "ultra"]}[case]
    out = tmp_path / "m"
    capsys.readouterr()
    assert main(["morph", *args, "--out", str(out), "--no-render"]) == 2
    line = one_error_line(capsys)
    assert {"missing": "INITIAL", "not_an_image": "INITIAL", "all_white": "no material", "missing_target": "TARGET",
            "quality": "ultra"}[case] in line, line
    assert not out.exists()


@pytest.mark.parametrize("bad", ["sim.steps=-3", "sim.n_grid=0"])
def test_a_bad_set_is_one_line_and_creates_nothing(tmp_path, capsys, bad):
    """The line names the key and the scene morph would have written, not its temporary file."""
    out = tmp_path / "m"
    capsys.readouterr()
    assert main(["morph", str(IMAGES / "circle_small.png"), str(IMAGES / "torus.png"), "--out", str(out),
                 "--set", bad]) == 2
    line = one_error_line(capsys)
    assert bad.split("=")[0] in line and f"morph's scene for {out / 'scene.toml'}" in line, line
    assert not out.exists()


def fresh_taichi():
    """A fresh Taichi runtime before each run (its kernels then load from the offline cache; tests/test_run.py)."""
    ti.reset()
    runtime.ensure(SimConfig(dtype="f64", arch="cpu"))


@pytest.fixture(scope="module")
def morphed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("morph")
    out = tmp / "m"
    fresh_taichi()
    code = main(["morph", str(IMAGES / "circle_small.png"), str(IMAGES / "torus.png"), "--out", str(out),
                 *tiny_run()])
    return code, out


def test_morph_runs_and_writes_its_scene(morphed):
    code, out = morphed
    assert code == 0
    assert (out / "scene.toml").is_file() and (out / "result.npz").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert 0.0 <= summary["iou"] <= 1.0 and 0.0 <= summary["mass_error"] <= 1.0
    assert summary["stop_reason"] == ["iteration budget"] and summary["iterations"] == 2
    assert summary["loss_final"] < summary["loss_initial"]
    scene = load_scene(out / "scene.toml")
    assert scene.sim.steps == 20 and scene.optimize.iterations == 2 and scene.optimize.max_seconds == 600.0
    assert summary["settings"] == json.loads(json.dumps(scene.to_dict()))  # the scene that ran is the one written
    assert not (out / "checkpoint.npz").exists()


def test_run_of_the_written_scene_reproduces_the_morph(morphed, tmp_path):
    code, out = morphed
    assert code == 0
    fresh_taichi()
    assert main(["run", str(out / "scene.toml"), "--out", str(tmp_path / "r"), "--no-render", "--quiet"]) == 0
    first = json.loads((out / "summary.json").read_text())
    again = json.loads((tmp_path / "r" / "summary.json").read_text())
    for key in ("loss_initial", "loss_final", "iou", "mass_error", "iterations", "stop_reason"):
        assert again[key] == first[key], key


def test_a_tiny_budget_ends_the_morph_with_its_result(tmp_path):
    out = tmp_path / "m"
    fresh_taichi()
    assert main(["morph", str(IMAGES / "circle_small.png"), str(IMAGES / "torus.png"), "--out", str(out),
                 *tiny_run(seconds=0.01, iterations=30)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert any(BUDGET_REASON in r for r in summary["stop_reason"]), summary["stop_reason"]
    assert summary["converged"] is False and summary["iterations"] < 30
    assert (out / "result.npz").is_file() and (out / "scene.toml").is_file()


def test_size_notes_name_a_tiny_body_and_a_target_of_another_size(tmp_path):
    """choose notes an INITIAL of fewer than FEW_PARTICLES particles, and a TARGET more than AREA_RATIO times larger
    or smaller (particle counts at one spacing, so areas); a pair of similar sizes gets no note."""
    dot = disk_image(tmp_path / "dot.png", (32, 32), radius=1.5)
    small = disk_image(tmp_path / "small.png", (32, 32), radius=8)
    big = disk_image(tmp_path / "big.png", (32, 32), radius=24)
    assert morph.choose(small, disk_image(tmp_path / "like.png", (30, 34), radius=10), "fast").notes == ()
    notes = morph.choose(dot, big, "fast").notes
    assert len(notes) == 2
    assert notes[0].startswith(f"note: INITIAL {dot} gives only ") and "particles on the 32x32 grid" in notes[0]
    assert notes[1].startswith(f"note: TARGET {big} has ") and "x the area of INITIAL" in notes[1]
    larger = morph.choose(small, big, "fast").notes
    assert len(larger) == 1 and "can cover the target only at 1/" in larger[0]
    smaller = morph.choose(big, small, "fast").notes
    assert len(smaller) == 1 and smaller[0].startswith(f"note: TARGET {small} has 1/") and "compress" in smaller[0]
    # the ratio in the note is that of the particle counts it gives (target / initial)
    n_target, n_initial = (int(t) for t in larger[0].split("(")[1].split(" particles")[0].split(" against "))
    assert n_target > morph.AREA_RATIO * n_initial >= morph.AREA_RATIO * morph.FEW_PARTICLES
    assert f"has {n_target / n_initial:.3g}x the area" in larger[0]


def test_a_target_too_thin_to_occupy_reports_no_iou(tmp_path, capsys):
    """A dot morphed toward a disk of ~100x its area: the notes go to stderr before the run, --quiet or not, and
    since no target node reaches 0.1 of the rest node mass, the iou is None in summary.json and "n/a" in the last
    line."""
    dot = disk_image(tmp_path / "dot.png", (32, 32), radius=1.5)
    big = disk_image(tmp_path / "big.png", (32, 32), radius=24)
    for quiet in (False, True):
        out = tmp_path / f"m{quiet}"
        fresh_taichi()
        options = [o for o in tiny_run() if quiet or o != "--quiet"]
        assert main(["morph", str(dot), str(big), "--out", str(out), *options]) == 0
        captured = capsys.readouterr()
        notes = [line for line in captured.err.splitlines() if line.startswith("mls-mpm: note: ")]
        assert len(notes) == 2 and notes[0].startswith("mls-mpm: note: INITIAL ") and " TARGET " in notes[1]
        assert json.loads((out / "summary.json").read_text())["iou"] is None
        last = captured.out.splitlines()[-1]
        assert "iou n/a (no target node holds 0.1 of the rest node mass" in last
        assert last.startswith("morph_dot_to_big: ") == quiet and "note:" not in captured.out


def test_a_white_on_black_mask_gets_a_note(tmp_path):
    """An image whose border is material (opaque, not white) is taken as everything but its white part, which a
    white shape on black is not meant as: choose notes it (and the same shape drawn black on white gets none)."""
    mask = np.zeros((64, 64, 3), np.uint8)
    yy, xx = np.mgrid[:64, :64] + 0.5
    mask[(xx - 32) ** 2 + (yy - 32) ** 2 < 20 ** 2] = 255
    Image.fromarray(mask).save(tmp_path / "mask.png")
    disk = disk_image(tmp_path / "disk.png", (32, 32), radius=20)
    notes = morph.choose(tmp_path / "mask.png", disk, "fast").notes
    assert len(notes) == 1 and notes[0].startswith(f"note: INITIAL {tmp_path / 'mask.png'}: 100% of its border is "
                                                   "material") and "invert the image" in notes[0]
    assert morph.choose(disk, disk, "fast").notes == ()
