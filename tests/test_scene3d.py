"""3D scenes (sim.dim = 3): keys and their defaults, problem.build's particles and (res,)^3 target grids, the
shipped *_3d scenes, and every refusal of bad 3D input: one line, exit 2, nothing written. No simulation runs:
each refusal comes before the simulator is built."""
from pathlib import Path

import numpy as np
import pytest
import trimesh

from mls_mpm.losses import ColorLoss, MassLoss, OTLoss
from mls_mpm.problem import build, iou, occupied, rest_node_mass
from mls_mpm.scene import SceneError, load_scene

from test_input_errors import refused  # mls-mpm ARGV in a folder: exit 2, one line, nothing written

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "scenes" / "images"
SHIPPED_3D = sorted((ROOT / "scenes").glob("*_3d.toml"))

BASE = """[scene]
initial = "shape:sphere?r=0.3"
target = "shape:torus?R=0.3&r=0.12"
[sim]
dim = 3
n_grid = 16
steps = 10
dt = 0.001
E = 100.0
particles_per_cell = 1
[control]
stride = 5
[loss]
grids = [8, 16]
"""


def write(folder, text, name="s3.toml"):
    path = Path(folder) / name
    path.write_text(text)
    return path


def edit(text, section, line):
    return text.replace(f"[{section}]\n", f"[{section}]\n{line}\n", 1)


def test_3d_defaults(tmp_path):
    s = load_scene(write(tmp_path, BASE))
    assert s.sim.dim == 3 and s.sim.gravity == (0.0, -9.8, 0.0) and s.target_shift == (0.0, 0.0, 0.0)
    assert s.region is None and s.repair is False and s.loss.target_scale == (1.0, 1.0, 1.0)
    assert s.initial == "shape:sphere?r=0.3&cx=0.5&cy=0.5&cz=0.5"
    d = s.to_dict()
    assert d["sim"]["dim"] == 3 and d["scene"]["repair"] is False and d["scene"]["target_shift"] == [0.0] * 3


@pytest.mark.parametrize("mode", ["surface", "volume", "particles", "mass"])
def test_3d_render_mode_key_takes_the_3d_modes(tmp_path, mode):
    s = load_scene(write(tmp_path, BASE + f'[render]\nmode = "{mode}"\n'))
    assert s.render.mode == mode and s.render.background == "white"
    assert s.to_dict()["render"]["mode"] == mode


def test_3d_build_makes_cubic_target_grids_of_the_body_mass(tmp_path):
    s = load_scene(write(tmp_path, BASE.replace("n_grid = 16", "n_grid = 24").replace("[8, 16]", "[12, 24]")))
    p = build(s)
    N = len(p.x0)
    assert p.x0.shape == (N, 3) and p.colors.shape == (N, 3) and p.target_points.shape[1] == 3
    assert isinstance(p.loss, MassLoss) and p.res == 24
    for grid, res in zip(p.target_mass_grids, (12, 24)):
        assert grid.shape == (res, res, res)
        assert grid.sum() == pytest.approx(N * s.sim.m_p, rel=1e-12)  # target_density "match"
    assert rest_node_mass(s.sim, 24) == pytest.approx(s.sim.density / 24 ** 3)
    target = p.target_mass_grids[1]
    rest = rest_node_mass(s.sim, 24)
    assert iou(occupied(target, rest), occupied(target, rest)) == 1.0
    # a torus around the centre: the centre node (its hole) is empty, its ring is occupied
    assert not occupied(target, rest)[12, 12, 12] and occupied(target, rest)[12 + 5, 12, 12]


def test_3d_target_shift_moves_the_target(tmp_path):
    text = BASE.replace("n_grid = 16", "n_grid = 24")
    p0 = build(load_scene(write(tmp_path, text)))
    p1 = build(load_scene(write(tmp_path, edit(text, "scene", "target_shift = [0.05, 0.0, -0.05]"))))
    np.testing.assert_allclose(p1.target_points - p0.target_points, np.tile([0.05, 0.0, -0.05], (len(p0.target_points), 1)),
                               atol=1e-15)


@pytest.mark.parametrize("kind, cls", [("ot", OTLoss), ("color", ColorLoss)])
def test_3d_ot_and_colour_losses_build(tmp_path, kind, cls):
    text = BASE.replace("[loss]\n", f'[loss]\nkind = "{kind}"\n')
    if kind == "color":
        text = text.replace('"shape:sphere?r=0.3"', f'"extrude:{IMAGES / "color_halves.png"}?depth=0.5"') \
                   .replace('"shape:torus?R=0.3&r=0.12"', f'"extrude:{IMAGES / "color_swap_target.png"}?depth=0.5"')
    p = build(load_scene(write(tmp_path, text)))
    assert isinstance(p.loss, cls) and all(g.target.shape[:3] == (g.res,) * 3 for g in p.loss.grids)
    if kind == "color":
        assert {tuple(c) for c in p.colors} == {(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)}


def test_3d_penalty_number_builds(tmp_path):
    p = build(load_scene(write(tmp_path, edit(BASE, "loss", "penalty = 5"))))
    alpha = p.loss.grids[1].alpha
    assert alpha.shape[:3] == (16, 16, 16) and set(np.unique(alpha)) == {1.0, 5.0}


def test_repaired_mesh_is_reported_in_the_problem_notes(tmp_path):
    ball = trimesh.creation.icosphere(subdivisions=2)
    trimesh.Trimesh(ball.vertices, ball.faces[1:], process=False).export(tmp_path / "open.obj")
    s = load_scene(write(tmp_path, edit(BASE.replace('"shape:sphere?r=0.3"', '"open.obj"'), "scene", "repair = true")))
    p = build(s)
    assert len(p.notes) == 1 and "repaired with trimesh's fill_holes" in p.notes[0] and len(p.x0) > 0


@pytest.mark.parametrize("path", SHIPPED_3D, ids=[p.stem for p in SHIPPED_3D])
def test_shipped_3d_scene_loads_and_builds(path):
    s = load_scene(path)
    p = build(s)
    N = len(p.x0)
    assert s.sim.dim == 3 and s.sim.dt <= s.sim.cfl_dt and 1000 < N < 20000, N
    for grid, res in zip(p.target_mass_grids, s.loss.grids):
        assert grid.shape == (res,) * 3 and grid.sum() == pytest.approx(N * s.sim.m_p, rel=1e-9)


def test_the_3d_scenes_named_by_the_issue_are_shipped():
    names = {p.stem for p in SHIPPED_3D}
    assert {"sphere_to_torus_3d", "sphere_to_two_spheres_3d", "sphere_to_A_3d", "box_to_ring_3d"} <= names
    loaded = [load_scene(p) for p in SHIPPED_3D]
    assert any(s.optimize.rounds > 1 for s in loaded) and any(s.loss.kind == "color" for s in loaded)


# ---- refusals: one line, exit 2, nothing written --------------------------------------------------------------

def flat_mesh(path):
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 1]]).export(path)


def open_mesh(path):
    ball = trimesh.creation.icosphere(subdivisions=2)
    trimesh.Trimesh(ball.vertices, ball.faces[1:], process=False).export(path)




@pytest.mark.parametrize("initial, make, extra, pattern", [
    ("ball.obj", None, "", r'scene\.initial = "ball\.obj": expected a mesh file \(.*ball\.obj: no such mesh file\)$'),
    ("ball.stl", lambda p: p.write_bytes(b"solid x\nfacet nonsense\n"), "",
     r'scene\.initial = ".*ball\.stl": expected a usable 3D shape \(.*ball\.stl: (not a mesh trimesh can read|holds '
     r'no triangles)'),
    ("ball.obj", lambda p: p.write_text(""), "",
     r'scene\.initial = ".*ball\.obj": expected a usable 3D shape \(.*ball\.obj: (holds no triangles|not a mesh)'),
    ("ball.obj", open_mesh, "", r"ball\.obj: not watertight: trimesh reports is_watertight = False, 3 edge\(s\) on "
                                r"one face only and 0 on more than two; fix the mesh, or set scene\.repair = true"),
    ("ball.obj", flat_mesh, "", r"ball\.obj: has no volume \(trimesh reports volume 0"),
    (str(IMAGES / "circle.png"), None, "", r"scene\.initial = \".*circle\.png\": expected a mesh path \(\.obj \.stl "
                                           r"\.ply \.off \.glb\), .* in a 3D scene \(a 2D image needs extrude:, e\.g\. "
                                           r"\"extrude:.*circle\.png\"\)$"),
    ("shape:sphere?r=0.001&cx=0.51&cy=0.52&cz=0.53", None, "",
     r"expected a shape that holds at least one particle \(no particle landed inside the shape; it is smaller than "
     r"the particle spacing \(0\.0625\) at n_grid 16\)$"),
    ("shape:cone", None, "", r'scene\.initial = "shape:cone": expected a shape \(unknown built-in shape'),
    (f"extrude:{IMAGES / 'nope.png'}", None, "", r"scene\.initial = .*: expected an image file \(.*nope\.png: no such "
                                                 r"image file\)$"),
    ("shape:sphere", None, "[sim]\ngravity = [0.0, -9.8]",
     r"sim\.gravity = \[0\.0, -9\.8\]: expected 3 numbers for sim\.dim = 3$"),
    ("shape:sphere", None, "[scene]\nregion = [0.2, 0.2, 0.8, 0.8]",
     r"scene\.region = \[0\.2, 0\.2, 0\.8, 0\.8\]: expected \[x0, y0, z0, x1, y1, z1\] with"),
    ("shape:sphere", None, "[scene]\ntarget_shift = [0.1, 0.0]",
     r"scene\.target_shift = \[0\.1, 0\.0\]: expected 3 numbers for sim\.dim = 3$"),
    ("shape:sphere", None, f"[loss]\npenalty = \"{IMAGES / 'circle.png'}\"",
     r"loss\.penalty = .*: expected a number with sim\.dim = 3"),
    ("shape:sphere", None, "[render]\nbackground = \"transparent\"",
     r'render\.background = "transparent": expected "white" with sim\.dim = 3 \(the 3D preview is drawn on white'),
    ("shape:sphere", None, "[render]\nmode = \"glass\"",
     r'render\.mode = "glass": expected one of "mass", "color", "particles", "surface", "volume"$'),
])
def test_bad_3d_input_is_one_line_exit_2_nothing_written(capsys, tmp_path, initial, make, extra, pattern):
    if make:
        make(tmp_path / initial)
    text = BASE.replace('"shape:sphere?r=0.3"', f'"{initial}"')
    if extra:
        section, line = extra.split("\n", 1)
        text = edit(text, section.strip("[]"), line) if section in text else f"{text}{section}\n{line}\n"
    scene = write(tmp_path, text)
    message = refused(capsys, tmp_path, "run", scene, "--no-render", "--out", tmp_path / "out")
    assert message.startswith(str(scene)) or str(tmp_path) in message
    import re
    assert re.search(pattern, message), message


def test_a_mesh_or_shape_in_a_2d_scene_is_refused(capsys, tmp_path):
    ball = trimesh.creation.icosphere(subdivisions=1)
    ball.export(tmp_path / "ball.obj")
    for value in ("ball.obj", "shape:sphere", f"extrude:{IMAGES / 'circle.png'}"):
        text = BASE.replace('"shape:sphere?r=0.3"', f'"{value}"').replace("dim = 3\n", "")
        message = refused(capsys, tmp_path, "run", write(tmp_path, text), "--no-render")
        assert "scene.initial" in message and message.endswith(
            "expected an image file in a 2D scene (meshes, shape: and extrude: need sim.dim = 3)"), message


def test_a_load_error_names_the_scene_file(tmp_path):
    with pytest.raises(SceneError, match=r"s3\.toml: sim\.dim = 4: expected 2 or 3"):
        load_scene(write(tmp_path, BASE.replace("dim = 3", "dim = 4")))


# ---- mls-mpm morph with two 3D shapes ------------------------------------------------------------------------

def test_morph_chooses_a_3d_scene_for_two_shapes(tmp_path):
    from mls_mpm import morph
    ball = trimesh.creation.icosphere(subdivisions=3)
    ball.export(tmp_path / "ball.stl")
    choice = morph.choose(str(tmp_path / "ball.stl"), "shape:torus?R=0.3&r=0.1", "fast")
    s = load_scene(write(tmp_path, choice.text, "scene.toml"))
    assert (s.sim.dim, s.sim.n_grid, s.sim.particles_per_cell, s.sim.gravity) == (3, 24, 1, (0.0, 0.0, 0.0))
    assert s.name == "morph_ball_to_torus" and s.initial == tmp_path / "ball.stl" and s.loss.kind == "ot"
    assert len(s.target_shift) == 3 and 100 <= s.sim.steps <= 400
    p = build(s)
    assert p.x0.shape[1] == 3 and p.target_mass_grids[0].shape == (12, 12, 12)
    # the target is moved onto the body's centre of mass
    np.testing.assert_allclose(p.target_points.mean(axis=0), p.x0.mean(axis=0), atol=1e-3)


@pytest.mark.parametrize("quality, n_grid, rounds, iterations, seconds", [
    ("fast", 24, 2, 30, 120.0), ("default", 32, 3, 150, 120.0), ("best", 32, 3, 150, 0.0)])
def test_3d_morph_qualities(tmp_path, quality, n_grid, rounds, iterations, seconds):
    """The 3D presets as README documents them (morph.QUALITIES_3D): three rounds at default and best, which took six
    pairs of shapes from outside the repository from iou 0.66-0.96 to 0.90-0.99, and two at fast, which took the 3D
    quality suite's worst pair from 0.60 to 0.84 (BENCHMARKS.md)."""
    from mls_mpm import morph
    s = load_scene(write(tmp_path, morph.choose("shape:sphere", "shape:torus", quality).text, "scene.toml"))
    got = (s.sim.n_grid, s.optimize.rounds, s.optimize.iterations, s.optimize.max_seconds)
    assert got == (n_grid, rounds, iterations, seconds)


@pytest.mark.parametrize("initial, pattern", [
    ("shape:cone", r"INITIAL shape:cone: expected a 3D shape \(unknown built-in shape 'cone'"),
    ("nope.obj", r"INITIAL nope\.obj: expected a 3D shape \(.*nope\.obj: no such mesh file\)$"),
])
def test_morph_refuses_bad_3d_input_in_one_line(capsys, tmp_path, initial, pattern):
    import re
    message = refused(capsys, tmp_path, "morph", initial, "shape:sphere", "--out", tmp_path / "m", "--no-render")
    assert re.search(pattern, message), message


def test_morph_names_the_shape_without_particles_and_repairs_a_mesh_when_asked(capsys, tmp_path):
    """A shape too small for one particle is named alone (TARGET here, not "INITIAL or TARGET"); a mesh that is not
    watertight is refused with the --set that repairs it, and with that --set the morph's scene repairs it."""
    import re
    from mls_mpm import morph
    tiny = "shape:sphere?r=0.001&cx=0.51&cy=0.52&cz=0.53"
    message = refused(capsys, tmp_path, "morph", "shape:sphere", tiny, "--out", tmp_path / "m", "--no-render")
    assert re.search(r"^TARGET shape:sphere\?r=0\.001.*: no particle landed inside the shape; it is smaller than "
                     r"the particle spacing \(0\.0312\) at n_grid 32; use a larger shape or a finer --set "
                     r"sim\.n_grid$", message), message
    open_mesh(tmp_path / "open.obj")
    message = refused(capsys, tmp_path, "morph", tmp_path / "open.obj", "shape:sphere", "--out", tmp_path / "m",
                      "--no-render")
    assert "fix the mesh, or set scene.repair = true (mls-mpm morph: --set scene.repair=true)" in message, message
    choice = morph.choose(str(tmp_path / "open.obj"), "shape:sphere", "fast", sets=["scene.repair=true"])
    p = build(load_scene(write(tmp_path, choice.text, "scene.toml")))
    assert len(p.notes) == 1 and "repaired with trimesh's fill_holes" in p.notes[0] and len(p.x0) > 0


@pytest.mark.parametrize("initial, target, dim, pattern", [
    (IMAGES / "circle.png", IMAGES / "torus.png", "3",
     r"INITIAL .*circle\.png: expected a 3D shape \(.*circle\.png: expected a mesh \(\.obj \.stl \.ply \.off \.glb\), "
     r"shape:NAME or extrude:IMAGE\)$"),
    ("shape:sphere", "shape:torus", "2", r"INITIAL shape:sphere: expected an image file"),
])
def test_morph_dim_flag_refuses_inputs_of_the_other_dimension(capsys, tmp_path, initial, target, dim, pattern):
    """`--dim 3` takes 3D shapes only (a 2D image needs extrude:), `--dim 2` images only: one line, exit 2."""
    import re
    message = refused(capsys, tmp_path, "morph", initial, target, "--dim", dim, "--out", tmp_path / "m",
                      "--no-render")
    assert re.search(pattern, message), message


def test_morph_dim_flag_is_parsed():
    from mls_mpm.cli import build_parser
    p = build_parser()
    assert p.parse_args(["morph", "a", "b"]).dim is None
    assert p.parse_args(["morph", "a", "b", "--dim", "3"]).dim == 3
    with pytest.raises(SystemExit):
        p.parse_args(["morph", "a", "b", "--dim", "4"])
