"""`mls-mpm bench quality` (mls_mpm/bench/quality.py) and its shape pairs (scenes/make_images.py): the pairs
exist, are sized and shaped as their names say and cover every category; make_images draws them the same twice;
options are refused in one line before anything runs; rows, the table and the CSV from pair processes faked in
a few lines of Python (one of them failing); and, where `mls-mpm morph` exists, one tiny pair end to end.
"""
import csv
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from mls_mpm import shapes
from mls_mpm.bench import pairs3d, quality
from mls_mpm.bench.quality import CATEGORIES, PAIRS, QUICK, TARGETS, TARGETS_3D, Target, judge, suite_figures
from mls_mpm.cli import build_parser, main
from mls_mpm.meshes import load_mesh

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def make_images():
    sys.path.insert(0, str(ROOT / "scenes"))
    try:
        import make_images

        yield make_images
    finally:
        sys.path.remove(str(ROOT / "scenes"))


def pixels(path):
    """The image as an (64, 64, 3) uint8 array and its material mask (every pixel that is not white)."""
    rgb = np.asarray(Image.open(path).convert("RGB"))
    return rgb, (rgb != 255).any(axis=-1)


def bodies(mask):
    """Pieces of material (8-connected) and holes (4-connected background not reaching the border)."""
    _, n_bodies = ndimage.label(mask, structure=np.ones((3, 3)))
    background, n = ndimage.label(~mask)
    border = set(np.unique(np.concatenate([background[0], background[-1], background[:, 0], background[:, -1]])))
    return n_bodies, len(set(range(1, n + 1)) - border)


# ---- the pairs ---------------------------------------------------------------------------------------------------

def test_pairs_cover_every_category():
    assert len(PAIRS) >= 14 and len({p.name for p in PAIRS}) == len(PAIRS)
    assert {p.category for p in PAIRS} == set(CATEGORIES)
    assert set(QUICK) <= {p.name for p in PAIRS} and len(QUICK) == 3


def test_every_pair_image_is_drawn_64x64_with_6_to_70_percent_material(make_images, tmp_path):
    """make_images writes exactly the pairs' two images each (no other), and they are the shipped ones."""
    make_images.main(tmp_path)
    written = sorted(p.name for p in (tmp_path / "pairs").iterdir())
    assert written == sorted(f"{p.name}_{role}.png" for p in PAIRS for role in ("initial", "target"))
    for pair in PAIRS:
        for path in (pair.initial, pair.target):
            assert (tmp_path / "pairs" / path.name).read_bytes() == path.read_bytes(), path.name
            rgb, mask = pixels(path)
            assert rgb.shape == (64, 64, 3), path.name
            assert 0.06 <= mask.mean() <= 0.70, (path.name, mask.mean())


def test_make_images_draws_the_pairs_identically_twice(make_images, tmp_path):
    make_images.main(tmp_path / "a")
    make_images.main(tmp_path / "b")
    names = sorted(p.name for p in (tmp_path / "a" / "pairs").iterdir())
    assert len(names) == 2 * len(PAIRS)
    for name in names:
        assert (tmp_path / "a" / "pairs" / name).read_bytes() == (tmp_path / "b" / "pairs" / name).read_bytes()


def area_ratio(name):
    pair = {p.name: p for p in PAIRS}[name]
    return pixels(pair.target)[1].sum() / pixels(pair.initial)[1].sum()


def test_area_ratio_pairs_shrink_to_a_third_and_grow_three_times():
    assert area_ratio("shrink_disk") == pytest.approx(1 / 3, rel=0.03)
    assert area_ratio("grow_square") == pytest.approx(3.0, rel=0.03)
    others = [p.name for p in PAIRS if p.category not in ("area 1/3", "area 3")]
    assert all(0.8 <= area_ratio(n) <= 1.2 for n in others), {n: round(area_ratio(n), 2) for n in others}


@pytest.mark.parametrize("name, initial, target", [
    # (pieces of material, holes) of the initial and the target image
    ("hole_opens", (1, 0), (1, 1)),
    ("hole_closes", (1, 1), (1, 0)),
    ("thin_ring", (1, 0), (1, 1)),
    ("split_two", (1, 0), (2, 0)),
    ("split_three", (1, 0), (3, 0)),
    ("merge_two", (2, 0), (1, 0)),
    ("letter_A", (1, 0), (1, 1)),
    ("letter_C", (1, 0), (1, 0)),
    ("letter_S", (1, 0), (1, 0)),
    ("letter_T", (1, 0), (1, 0)),
    ("letter_L_thin", (1, 0), (1, 0)),
])
def test_pair_topology(name, initial, target):
    pair = {p.name: p for p in PAIRS}[name]
    assert bodies(pixels(pair.initial)[1]) == initial
    assert bodies(pixels(pair.target)[1]) == target


def test_off_centre_targets_are_off_centre():
    """The material's centroid (pixels from the image centre, y down): top right for corner_disk, left for the
    crescent, while the initial disks are centred."""
    def centroid(path):
        rows, cols = np.nonzero(pixels(path)[1])
        return cols.mean() + 0.5 - 32, rows.mean() + 0.5 - 32

    pairs = {p.name: p for p in PAIRS}
    for name in ("corner_disk", "side_crescent"):
        assert np.allclose(centroid(pairs[name].initial), 0, atol=0.6), name
    cx, cy = centroid(pairs["corner_disk"].target)
    assert cx > 10 and cy < -10
    cx, cy = centroid(pairs["side_crescent"].target)
    assert cx < -6 and abs(cy) < 0.6


def test_thin_parts_are_six_pixels_thick():
    """The ring's and the L's strokes: 6 material pixels along a line across them (no thinner than ~1 cell)."""
    pairs = {p.name: p for p in PAIRS}
    ring = pixels(pairs["thin_ring"].target)[1]
    assert ring[32, :32].sum() == 6 and ring[:32, 32].sum() == 6
    L = pixels(pairs["letter_L_thin"].target)[1]
    assert L[30, :].sum() == 6 and L[:, 30].sum() == 6


def test_colour_pair_swaps_red_and_blue():
    pair = {p.name: p for p in PAIRS}["color_bar_to_disk"]
    for path, left, right in ((pair.initial, (255, 0, 0), (0, 0, 255)), (pair.target, (0, 0, 255), (255, 0, 0))):
        rgb, mask = pixels(path)
        colours = {tuple(c) for c in rgb[mask]}
        assert colours == {left, right}, path.name
        assert tuple(rgb[32, 20]) == left and tuple(rgb[32, 44]) == right, path.name


# ---- the 3D pairs (pairs3d.py) -------------------------------------------------------------------------------------

PAIRS_3D = {p.name: p for p in pairs3d.PAIRS}


def test_3d_pairs_cover_every_category_with_names_of_their_own():
    assert len(pairs3d.PAIRS) >= 10 and len(PAIRS_3D) == len(pairs3d.PAIRS)
    assert {p.category for p in pairs3d.PAIRS} == set(pairs3d.CATEGORIES)
    assert set(pairs3d.QUICK) <= set(PAIRS_3D) and len(pairs3d.QUICK) == 3
    assert not set(PAIRS_3D) & {p.name for p in PAIRS}  # a name says which suite it is in
    used = {t for p in pairs3d.PAIRS for t in (p.initial_text, p.target_text) if t in pairs3d.MESHES}
    assert used == set(pairs3d.MESHES)  # every mesh is morphed, and in four formats
    assert {Path(m).suffix for m in used} == {".obj", ".ply", ".stl", ".off"}


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    return pairs3d.write_meshes(tmp_path_factory.mktemp("meshes"))


def test_3d_meshes_are_written_the_same_twice_and_read_as_a_users_are(meshes, tmp_path):
    again = pairs3d.write_meshes(tmp_path / "again", ["torus.obj", "bar.stl"])
    assert sorted(p.name for p in again.iterdir()) == ["bar.stl", "torus.obj"]  # only those asked for, no temp
    for name in ("torus.obj", "bar.stl"):
        assert (again / name).read_bytes() == (meshes / name).read_bytes(), name
    for name in pairs3d.MESHES:
        tri, notes = load_mesh(meshes / name)  # watertight with volume, or it raises
        assert len(tri) >= 12 and notes == [], name


def voxels(text, meshes, n=40):
    """The shape fitted into the unit cube (its frame's larger side n cells), as a boolean (n, n, n) array of the
    cell centres inside it."""
    pair = pairs3d.Pair3D("v", "thin", "", text, text)
    solid = shapes.solid(pair.inputs(meshes)[0])
    side = max(solid.hi - solid.lo)
    c = (np.arange(n) + 0.5) / n * side
    grid = np.stack(np.meshgrid(c, c, c, indexing="ij"), axis=-1).reshape(-1, 3) + solid.lo
    return np.asarray(solid.inside(grid)).reshape(n, n, n), side / n


@pytest.mark.parametrize("name, initial, target", [
    # (pieces of material, Euler number: pieces - tunnels + cavities) of the initial and the target shape
    ("shrink_ball", (1, 1), (1, 1)),
    ("grow_box", (1, 1), (1, 1)),
    ("corner_ball", (1, 1), (1, 1)),
    ("capsule_to_ring", (1, 1), (1, 0)),
    ("box_to_torus", (1, 1), (1, 0)),
    ("torus_to_ball", (1, 0), (1, 1)),
    ("ball_to_two", (1, 1), (2, 2)),
    ("two_to_bar", (2, 2), (1, 1)),
    ("ball_to_bar", (1, 1), (1, 1)),
    ("cone_to_cylinder", (1, 1), (1, 1)),
    ("color_slab", (1, 1), (1, 1)),
])
def test_3d_pair_topology(name, initial, target, meshes):
    from skimage.measure import euler_number

    pair = PAIRS_3D[name]
    for text, want in ((pair.initial_text, initial), (pair.target_text, target)):
        mask, _ = voxels(text, meshes)
        pieces = ndimage.label(mask, structure=np.ones((3, 3, 3)))[1]
        assert (pieces, euler_number(mask, connectivity=3)) == want, (name, text)


def volume(text, meshes, fitted=False, n=200_000):
    """The shape's volume in its frame's units, by n random points (about 1% off); fitted: once its frame is
    scaled to a larger side of 1, as the morph fits every shape into the same region."""
    pair = pairs3d.Pair3D("v", "thin", "", text, text)
    solid = shapes.solid(pair.inputs(meshes)[0])
    box = solid.hi - solid.lo
    points = solid.lo + np.random.default_rng(0).random((n, 3)) * box
    inside = np.asarray(solid.inside(points)).mean() * np.prod(box)
    return inside / max(box) ** 3 if fitted else inside


def test_3d_volume_ratios_are_as_the_pairs_say(meshes):
    def ratio(name, fitted=False):
        p = PAIRS_3D[name]
        return volume(p.target_text, meshes, fitted) / volume(p.initial_text, meshes, fitted)

    assert ratio("shrink_ball") == pytest.approx(1 / 3, rel=0.04)
    assert ratio("grow_box") == pytest.approx(3.0, rel=0.04)
    assert ratio("ball_to_bar", fitted=True) == pytest.approx(1 / 4.7, rel=0.04)
    # built-ins keep their sizes in the unit cube: as their phrases say, or the same volume
    for name, want in (("corner_ball", 1.0), ("box_to_torus", 0.68), ("ball_to_two", 0.59), ("two_to_bar", 1.0)):
        assert ratio(name) == pytest.approx(want, rel=0.04), name
        assert (f" of {want:g} its volume" in PAIRS_3D[name].tests) == (want != 1.0), name


def test_corner_ball_target_sits_in_a_corner(meshes):
    mask, h = voxels(PAIRS_3D["corner_ball"].target_text, meshes)
    centre = (np.argwhere(mask).mean(axis=0) + 0.5) * h
    assert np.allclose(centre, 0.72, atol=0.01) and np.allclose(
        (np.argwhere(voxels(PAIRS_3D["corner_ball"].initial_text, meshes)[0]).mean(axis=0) + 0.5) * h, 0.5, atol=0.01)


def test_colour_slab_extrudes_the_colour_pair_and_its_images_are_checked():
    pair = PAIRS_3D["color_slab"]
    two_d = {p.name: p for p in PAIRS}["color_bar_to_disk"]
    assert pair.images() == [two_d.initial, two_d.target]
    assert pairs3d.PAIRS_DIR == quality.PAIRS_DIR
    assert PAIRS_3D["torus_to_ball"].images() == []


# ---- options -----------------------------------------------------------------------------------------------------

def test_bench_quality_options_parse():
    a = build_parser().parse_args(["bench", "quality", "--quick", "--workers", "2", "--quality", "best", "--pairs",
                                   "split_two,letter_A", "--set", "sim.n_grid=32", "--set", "optimize.iterations=1"])
    assert (a.what, a.quick, a.workers, a.quality, a.pairs) == ("quality", True, 2, "best", "split_two,letter_A")
    assert a.set == ["sim.n_grid=32", "optimize.iterations=1"]
    a = build_parser().parse_args(["bench", "quality"])
    assert (a.workers, a.quality, a.pairs, a.set, a.out) == (None, None, None, [], None)


@pytest.fixture
def nothing_runs(monkeypatch):
    def run(*args, **kwargs):
        raise AssertionError("a pair ran before the options were checked")

    monkeypatch.setattr(quality, "run_pair", run)


@pytest.mark.parametrize("argv, says", [
    (["bench", "quality", "--pairs", "split_two,no_such,other"], "bench quality: --pairs no_such,other: no such "
                                                                 "pair; expected names from shrink_disk, "),
    (["bench", "quality", "--pairs", ","], "bench quality: --pairs: expected pair names separated by commas"),
    (["bench", "quality", "--workers", "0"], "bench: argument --workers: expected an integer >= 1, got '0'"),
    (["bench", "quality", "--quality", "good"], "bench: argument --quality: invalid choice: 'good'"),
    (["bench", "quality", "--quick", "--pairs", "split_two"], "bench quality: --quick and --pairs: --quick picks"),
    (["bench", "quality", "--arch", "gpu"], "bench quality: --arch applies to bench gradient only; drop it"),
    (["bench", "quality", "--max-seconds", "60"], "bench quality: --max-seconds 60: expected seconds > 0, with "
                                                  "bench tradeoff only"),
    (["bench", "quality", "s.toml"], "bench quality: SCENE s.toml: a scene applies to bench tradeoff only"),
    (["bench", "gradient", "--workers", "2"], "bench gradient: --workers applies to bench quality only; drop it"),
    (["bench", "scaling", "--quality", "fast"], "bench scaling: --quality applies to bench quality only; drop it"),
    (["bench", "tradeoff", "s.toml", "--pairs", "split_two"], "bench tradeoff: --pairs applies to bench quality "
                                                              "only"),
    (["bench", "scaling", "--set", "sim.n_grid=32"], "bench scaling: --set applies to bench quality only"),
    (["bench", "gradient", "--warm-cache"], "bench gradient: --warm-cache applies to bench quality only"),
    (["bench", "quality", "--out", "/proc/quality"], "--out /proc/quality: cannot create the folder"),
    (["bench", "quality", "--dim", "3", "--pairs", "box_to_torus,shrink_disk"], "bench quality: --pairs "
     "shrink_disk: no such pair (shrink_disk is a pair of --dim 2); expected names from shrink_ball, grow_box, "),
    (["bench", "quality", "--pairs", "box_to_torus"], "bench quality: --pairs box_to_torus: no such pair "
                                                      "(box_to_torus is a pair of --dim 3); expected names from "),
    (["bench", "quality", "--dim", "4"], "bench: argument --dim: invalid choice: 4"),
    (["bench", "scaling", "--dim", "3"], "bench scaling: --dim applies to bench gradient and bench quality only"),
])
def test_bench_quality_options_refused(argv, says, capsys, nothing_runs):
    """One line, exit 2, nothing run (s.toml does not exist: no scene is read)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mls-mpm: error: {says}") and len(err.splitlines()) == 1, err


def test_missing_pair_image_refused_before_anything_runs(tmp_path, monkeypatch, capsys, nothing_runs):
    monkeypatch.setattr(quality, "PAIRS_DIR", tmp_path / "pairs")
    assert main(["bench", "quality", "--quick", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err == (f"mls-mpm: error: bench quality: {tmp_path / 'pairs' / 'corner_disk_initial.png'}: no such "
                   "image (6 missing); draw them with python scenes/make_images.py\n")
    assert not (tmp_path / "out").exists()


# ---- rows, verdicts, the table -----------------------------------------------------------------------------------

def test_threads_per_worker_and_the_morph_command(monkeypatch):
    monkeypatch.setattr(quality.os, "sched_getaffinity", lambda pid: set(range(16)))
    assert [quality.threads_per_worker(n) for n in (1, 2, 3, 16, 40)] == [16, 8, 5, 1, 1]
    pair = PAIRS[0]
    cmd = quality.morph_command(pair, Path("o/p"), "fast", 8, ["sim.threads=1", "sim.n_grid=32"])
    assert cmd[:4] == [sys.executable, "-m", "mls_mpm.cli", "morph"]
    assert cmd[4:] == [str(pair.initial), str(pair.target), "--out", "o/p", "--quality", "fast", "--no-render",
                       "--quiet", "--set", "sim.threads=8", "--set", "sim.threads=1", "--set", "sim.n_grid=32"]


def test_judge_against_the_targets():
    row = {"iou": 0.95, "mass_error": 0.05, "wall_seconds": 100.0}
    assert judge(row, TARGETS["default"]) == "pass"
    assert judge(dict(row, iou=0.85, wall_seconds=130.0), TARGETS["default"]) == \
        "fail: iou 0.850 < 0.90, wall 130 s > 120 s"
    assert judge(dict(row, mass_error=0.2), TARGETS["default"]) == "fail: mass_error 0.200 > 0.15"
    assert judge({"iou": 0.85, "mass_error": 0.5, "wall_seconds": 29.0}, TARGETS["fast"]) == "pass"
    assert judge({"iou": 0.85, "wall_seconds": 31.0}, TARGETS["fast"]) == "fail: wall 31 s > 30 s"
    assert judge({"iou": 0.95, "mass_error": 0.05, "wall_seconds": 900.0}, TARGETS["best"]) == "pass"
    assert judge({"wall_seconds": 1.0}, Target(0.9, 0.15)) == "fail: iou - < 0.90, mass_error - > 0.15"
    assert judge({"error": "exit 1: boom", "wall_seconds": 1.0}, TARGETS["default"]) == "error: exit 1: boom"


def test_suite_worst_and_median():
    rows = [{"pair": "a", "iou": 0.9, "mass_error": 0.1}, {"pair": "b", "iou": 0.99, "mass_error": 0.02},
            {"pair": "c", "iou": 0.95, "mass_error": 0.3}, {"pair": "d", "error": "exit 1: x"}]
    assert suite_figures(rows) == {"iou": (0.9, 0.95, "a"), "mass_error": (0.3, 0.1, "c")}
    assert suite_figures(rows[3:]) == {}


FAKE_MORPH = """
import json, sys
from pathlib import Path
out, name = Path(sys.argv[1]), Path(sys.argv[2]).name
if name.startswith("split_two"):
    sys.exit("mls-mpm: error: first line\\nmls-mpm: simulation stopped: step 7 left the grid")
out.mkdir(parents=True)
iou = {"corner_disk_initial.png": 0.97, "letter_T_initial.png": 0.78}[name]
summary = {"iou": iou, "mass_error": 0.04, "mass_outside_target": 0.01, "wall_seconds": 5.5,
           "stop_reason": ["iteration budget"]}
(out / "summary.json").write_text(json.dumps(summary))
"""


def test_quick_suite_with_faked_morphs_writes_the_table_and_csv(tmp_path, monkeypatch, capsys):
    """Three pair processes (a few lines of Python standing in for morph), two at a time: one passes, one misses
    the fast iou target, one exits 1; the table and the CSV hold each, in suite order, and the suite goes on."""
    def fake(pair, out_dir, q, threads, overrides=(), meshes=None):
        assert (q, list(overrides), meshes) == ("fast", ["sim.n_grid=32"], None)
        return [sys.executable, "-c", FAKE_MORPH, str(out_dir), str(pair.initial)]

    monkeypatch.setattr(quality, "morph_command", fake)
    out = tmp_path / "q"
    assert main(["bench", "quality", "--quick", "--workers", "2", "--out", str(out), "--set", "sim.n_grid=32"]) == 0
    printed = capsys.readouterr().out.splitlines()
    progress = [ln for ln in printed if ln.startswith("[")]
    assert sorted(ln.split()[1] for ln in progress) == sorted(QUICK) and progress[0].startswith("[1/3]")
    md = (out / "quality.md").read_text()
    assert md.rstrip("\n") in "\n".join(printed)
    table = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| pair")]
    assert [ln.split(" | ")[0] for ln in table] == ["| corner_disk", "| split_two", "| letter_T"]
    assert table[0].startswith("| corner_disk | disk to the same disk in the top-right corner | 0.970 | 0.040 | "
                               "0.010 | - | ") and table[0].endswith(" | pass |")
    assert table[1].endswith(" | error: exit 1: mls-mpm: simulation stopped: step 7 left the grid |")
    assert table[2].endswith(" | fail: iou 0.780 < 0.80 |")
    assert "- iou: worst 0.780 (letter_T), median 0.875" in md and "- mass_error: worst 0.040" in md
    assert "- 1 of 3 pairs meet the target; 1 did not finish" in md
    assert f"- command: `mls-mpm bench quality --quick --quality fast --workers 2 --out {out} --set " \
           "sim.n_grid=32`" in md
    assert md.startswith("`mls-mpm morph --quality fast` on 3 shape pairs (scenes/images/pairs/), 2 at a time, ")
    assert "- CPU: " in md and "Target per pair: iou >= 0.80, wall <= 30 s (wall: the whole process" in md
    with open(out / "quality.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["pair"] for r in rows] == list(QUICK)
    assert (rows[0]["iou"], rows[0]["mass_error"], rows[0]["run_seconds"], rows[0]["stop_reason"],
            rows[0]["result"]) == ("0.97", "0.04", "5.50", "iteration budget", "pass")
    assert rows[1]["iou"] == "" and rows[1]["result"].startswith("error: exit 1: ")
    assert float(rows[2]["wall_seconds"]) > 0
    assert sorted(p.name for p in out.iterdir()) == ["corner_disk", "letter_T", "quality.csv", "quality.md"]


FAKE_MORPH_3D = """
import json, sys
from pathlib import Path
from mls_mpm.shapes import solid
out, initial, target = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
for text in (initial, target):
    solid(text)  # a mesh path that is missing or broken, or a bad shape text, raises here
out.mkdir(parents=True)
iou = 0.95 if initial.endswith("torus.obj") else 0.85
json.dump({"iou": iou, "mass_error": 0.05, "wall_seconds": 1.0}, open(out / "summary.json", "w"))
"""


def test_3d_suite_with_faked_morphs_writes_its_meshes_first(tmp_path, monkeypatch, capsys):
    """--dim 3: the meshes its pairs morph are written into <out>/meshes/ before any runs, passed as paths (a
    stand-in morph reads them as shapes), and the rows are judged against the 3D targets."""
    def fake(pair, out_dir, q, threads, overrides=(), meshes=None):
        assert meshes == out / "meshes" and q == "default"
        return [sys.executable, "-c", FAKE_MORPH_3D, str(out_dir), *pair.inputs(meshes)]

    monkeypatch.setattr(quality, "morph_command", fake)
    out = tmp_path / "q3"
    assert main(["bench", "quality", "--dim", "3", "--pairs", "torus_to_ball,ball_to_two", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("quality benchmark: 2 3D pairs at --quality default, ")
    assert sorted(p.name for p in (out / "meshes").iterdir()) == ["ball.obj", "torus.obj"]
    md = (out / "quality.md").read_text()
    assert md.startswith("`mls-mpm morph --quality default` on 2 shape pairs (3D: built-in solids, trimesh meshes, ")
    assert f"Target per pair: {TARGETS_3D['default'].describe()} " in md and "wall <= 180 s" in md
    rows = [ln for ln in md.splitlines() if ln.startswith("| ") and not ln.startswith("| pair")]
    assert rows[0].startswith("| torus_to_ball | torus mesh to a ball mesh | 0.950 | 0.050 | ") and \
        rows[0].endswith(" | pass |")
    assert rows[1].startswith("| ball_to_two | ") and rows[1].endswith(" | fail: iou 0.850 < 0.90 |")
    assert f"- command: `mls-mpm bench quality --dim 3 --quality default --workers 1 --out {out} --pairs " \
           "torus_to_ball,ball_to_two`" in md


def test_3d_morph_command_passes_shape_texts_and_mesh_paths(tmp_path):
    cmd = quality.morph_command(PAIRS_3D["capsule_to_ring"], tmp_path / "o", "fast", 2, (), tmp_path / "m")
    assert cmd[4:6] == [str(tmp_path / "m" / "capsule.obj"), str(tmp_path / "m" / "ring.ply")]
    cmd = quality.morph_command(PAIRS_3D["box_to_torus"], tmp_path / "o", "fast", 2)
    assert cmd[4:6] == ["shape:box", "shape:torus"]


CACHE_PROBE = """
import json, os, sys
out = sys.argv[1]
os.makedirs(out, exist_ok=True)
cache = os.environ.get("TI_OFFLINE_CACHE_FILE_PATH")
seen = {"cache": cache, "empty": cache is not None and os.path.isdir(cache) and not os.listdir(cache)}
json.dump(dict(seen, iou=0.9, mass_error=0.0), open(os.path.join(out, "summary.json"), "w"))
"""


def test_each_pair_compiles_in_an_empty_cache_unless_warm(tmp_path, monkeypatch):
    """A pair's process gets an empty Taichi offline cache of its own, removed afterwards (a new shape compiles
    every kernel: the particle count is compiled in); --warm-cache leaves Taichi's cache as the user has it."""
    monkeypatch.setattr(quality, "morph_command", lambda pair, out_dir, *a: [sys.executable, "-c", CACHE_PROBE,
                                                                           str(out_dir)])
    monkeypatch.delenv("TI_OFFLINE_CACHE_FILE_PATH", raising=False)
    caches = []
    for warm in (False, False, True):
        out = tmp_path / f"p{len(caches)}"
        row = quality.run_pair(PAIRS[0], out, "fast", 1, warm_cache=warm)
        assert row["iou"] == 0.9, row
        caches.append(json.loads((out / "summary.json").read_text()))
    assert caches[0]["empty"] and caches[1]["empty"] and caches[0]["cache"] != caches[1]["cache"]
    assert not os.path.exists(caches[0]["cache"]) and not os.path.exists(caches[1]["cache"])
    assert caches[2]["cache"] is None
    a = build_parser().parse_args(["bench", "quality", "--warm-cache"])
    assert a.warm_cache is True
    assert "--warm-cache" in quality.command_line("default", False, 1, "o", None, (), warm_cache=True)
    assert "empty Taichi cache" in quality.table([], "fast", 1, 2, "c") and \
        "Taichi's cache as it was" in quality.table([], "fast", 1, 2, "c", warm_cache=True)


# ---- end to end ----------------------------------------------------------------------------------------------------

def morph_exists():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return "morph" in sub.choices


@pytest.mark.slow
@pytest.mark.skipif(not morph_exists(), reason="`mls-mpm morph` is not a command of this version yet (issue 11)")
def test_one_tiny_pair_end_to_end(tmp_path, capsys):
    """split_two through the real morph at a negligible size: the row holds the iou of its summary.json."""
    out = tmp_path / "q"
    argv = ["bench", "quality", "--pairs", "split_two", "--quality", "fast", "--out", str(out), "--set",
            "sim.steps=20", "--set", "optimize.iterations=1", "--set", "sim.n_grid=32"]
    assert main(argv) == 0
    summary = json.loads((out / "split_two" / "summary.json").read_text())
    assert (out / "split_two" / "scene.toml").is_file()
    with open(out / "quality.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["pair"] == "split_two" and not row["result"].startswith("error"), row
    assert float(row["iou"]) == pytest.approx(summary["iou"], abs=1e-6)
    assert float(row["mass_error"]) == pytest.approx(summary["mass_error"], abs=1e-6)
    (line,) = [ln for ln in (out / "quality.md").read_text().splitlines() if ln.startswith("| split_two |")]
    assert f" | {summary['iou']:.3f} | {summary['mass_error']:.3f} | " in line
    assert "[1/1] split_two" in capsys.readouterr().out
