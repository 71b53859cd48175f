"""3D shapes as particles (mls_mpm/shapes.py, mls_mpm/meshes.py): counts against volumes, fitting and centring,
mesh formats, the inside test against an analytic solid, extrusion, the 3D splat, and each refusal's line.
No simulation: nothing here compiles a kernel."""
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from mls_mpm import shapes
from mls_mpm.images import default_region, load_image, material, pixel_of, splat_grid
from mls_mpm.meshes import MeshError, contains, load_mesh

ROOT = Path(__file__).resolve().parents[1]
LETTER_A = ROOT / "scenes" / "images" / "pairs" / "letter_A_target.png"
N_GRID, PPC = 32, 8
REGION = default_region(N_GRID, 3, 3)  # [5/32, 27/32]^3
WIDTH = REGION[3] - REGION[0]
CELL_VOLUME = (1.0 / N_GRID) ** 3


def particles(text, **kw):
    return shapes.sample(shapes.solid(text), N_GRID, PPC, **kw)


@pytest.fixture(scope="module")
def icosphere():
    return trimesh.creation.icosphere(subdivisions=3, radius=2.0)


# ---- counts and volumes ------------------------------------------------------------------------------------

def test_sphere_count_is_ppc_times_its_volume_in_cells():
    x, c = particles("shape:sphere?r=0.3")
    r = 0.3 * WIDTH  # the unit-cube frame fitted into the region
    expected = PPC * (4 / 3 * math.pi * r ** 3) / CELL_VOLUME
    assert abs(len(x) - expected) < 0.02 * expected, (len(x), expected)
    assert np.all(np.linalg.norm(x - 0.5, axis=1) < r) and c.shape == (len(x), 3) and np.all(c == 0)


def test_mesh_sphere_count_is_ppc_times_trimesh_volume(tmp_path, icosphere):
    path = tmp_path / "ball.obj"
    icosphere.export(path)
    x, _ = shapes.sample(shapes.solid(path), N_GRID, PPC)
    scale = WIDTH / icosphere.extents.max()  # its bounding box fitted into the region
    expected = PPC * icosphere.volume * scale ** 3 / CELL_VOLUME
    assert abs(len(x) - expected) < 0.02 * expected, (len(x), expected)


def test_every_mesh_format_gives_the_same_particles(tmp_path, icosphere):
    got = []
    for suffix in (".obj", ".stl", ".ply", ".off", ".glb"):
        path = tmp_path / f"ball{suffix}"
        icosphere.export(path)
        got.append(shapes.sample(shapes.solid(path), 16, 1)[0])
    for x in got[1:]:
        np.testing.assert_allclose(x, got[0], rtol=0, atol=0)


def test_inside_test_matches_an_analytic_torus_away_from_its_facets():
    R, r = 0.6, 0.25
    mesh = trimesh.creation.torus(R, r, major_sections=96, minor_sections=48)
    p = np.random.default_rng(0).uniform(-1, 1, (40000, 3))
    dist = np.hypot(np.hypot(p[:, 0], p[:, 1]) - R, p[:, 2]) - r  # signed distance to the exact torus
    far = np.abs(dist) > 0.01  # the 96 x 48 facets lie within ~0.002 of it
    got = contains(mesh.triangles, p)
    assert np.array_equal(got[far], dist[far] < 0) and 0.05 < got.mean() < 0.3


# ---- fitting and centring ----------------------------------------------------------------------------------

def test_a_mesh_is_fitted_aspect_kept_and_centred(tmp_path):
    box = trimesh.creation.box((2.0, 1.0, 0.5))
    box.apply_translation((10.0, -3.0, 7.0))
    path = tmp_path / "slab.stl"
    box.export(path)
    x, _ = shapes.sample(shapes.solid(path), N_GRID, PPC)
    lo, hi = x.min(axis=0), x.max(axis=0)
    np.testing.assert_allclose((lo + hi) / 2, 0.5, atol=1.0 / N_GRID / 2)
    np.testing.assert_allclose(hi - lo, [WIDTH, WIDTH / 2, WIDTH / 4], atol=1.0 / N_GRID / 2)


def test_a_builtin_shape_keeps_its_place_in_its_unit_cube_frame():
    x, _ = particles("shape:box?sx=0.5&sy=0.25&sz=0.25&cx=0.3")
    lo, hi = x.min(axis=0), x.max(axis=0)
    frame = lambda u: REGION[0] + WIDTH * np.asarray(u)  # noqa: E731
    np.testing.assert_allclose(lo, frame([0.05, 0.375, 0.375]), atol=0.6 / N_GRID / 2)
    np.testing.assert_allclose(hi, frame([0.55, 0.625, 0.625]), atol=0.6 / N_GRID / 2)


def test_a_region_box_takes_the_shape():
    region = (0.3, 0.2, 0.4, 0.7, 0.5, 0.6)  # the smallest side (z, 0.2) limits the scale
    x, _ = particles("shape:sphere?r=0.5", region=region)
    np.testing.assert_allclose((x.min(axis=0) + x.max(axis=0)) / 2, [0.5, 0.35, 0.5], atol=1.0 / N_GRID / 2)
    assert np.all(np.ptp(x, axis=0) <= 0.2 + 1e-12) and np.all(np.ptp(x, axis=0) > 0.2 - 1.0 / N_GRID)


def test_sampling_is_deterministic_for_a_seed():
    a, b, c = (particles("shape:torus", seed=s)[0] for s in (4, 4, 5))
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_extrude_puts_every_particle_over_a_material_pixel_in_a_centred_slab():
    rgba = load_image(LETTER_A)
    x, colors = particles(f"extrude:{LETTER_A}?depth=0.5")
    row, col, inside = pixel_of(x[:, :2], rgba.shape, REGION[:2] + REGION[3:5])  # the 2D fit of its x and y
    assert inside.all() and material(rgba)[row, col].all()
    thick = 0.5 * WIDTH  # depth 0.5 of the image's larger side
    assert x[:, 2].min() >= 0.5 - thick / 2 and x[:, 2].max() <= 0.5 + thick / 2
    assert np.ptp(x[:, 2]) > thick - 1.0 / N_GRID
    np.testing.assert_array_equal(colors, rgba[row, col, :3])


def test_3d_splat_keeps_mass_and_centroid():
    x, _ = particles("shape:two_spheres")
    grid = splat_grid(x, 0.5, 24)
    assert grid.shape == (24, 24, 24)
    assert grid.sum() == pytest.approx(0.5 * len(x), rel=1e-12)  # partition of unity
    nodes = np.stack(np.meshgrid(*[np.arange(24) / 24] * 3, indexing="ij"), -1)
    centroid = (grid[..., None] * nodes).sum(axis=(0, 1, 2)) / grid.sum()
    np.testing.assert_allclose(centroid, x.mean(axis=0), atol=1e-12)  # the cubic B-spline reproduces linears


# ---- refusals ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, pattern", [
    ("shape:cone", r"unknown built-in shape 'cone'; expected one of shape:sphere, shape:box"),
    ("shape:sphere?radius=1", r"shape:sphere: unknown parameter 'radius'; expected r, cx, cy, cz"),
    ("shape:sphere?r=-1", r"shape:sphere: r=-1: expected a number > 0"),
    ("shape:torus?axis=w", r"shape:torus: axis=w: expected x, y or z"),
    ("shape:torus?R=0.1&r=0.2", r"shape:torus: r=0.2: expected a tube radius below the ring radius R=0.1"),
    ("shape:two_spheres?r=0.2&d=0.3", r"d=0.3: expected a centre distance above 2 r = 0.4"),
    ("shape:sphere?r=0.6", r"shape:sphere: spans \[-0.1, -0.1, -0.1\] to \[1.1, 1.1, 1.1\]: expected a shape inside"),
])
def test_bad_shape_texts_are_refused_in_one_line(text, pattern):
    with pytest.raises(shapes.ShapeError, match=pattern) as e:
        shapes.solid(text)
    assert "\n" not in str(e.value)


def test_a_shape_below_the_particle_spacing_is_refused():
    with pytest.raises(shapes.ShapeError, match=r"no particle landed inside the shape; it is smaller than the "
                                                r"particle spacing \(0.0625\) at n_grid 16"):
        shapes.sample(shapes.solid("shape:sphere?r=0.001&cx=0.51&cy=0.52&cz=0.53"), 16, 1)


def open_sphere(icosphere, missing=1):
    return trimesh.Trimesh(icosphere.vertices, icosphere.faces[missing:], process=False)


@pytest.mark.parametrize("make, pattern", [
    (None, r"ball\.obj: no such mesh file$"),
    (lambda p, s: p.write_text(""), r"ball\.obj: (holds no triangles|not a mesh trimesh can read)"),
    (lambda p, s: p.write_bytes(b"\x00\xff garbage \x01" * 50), r"ball\.obj: (holds no triangles|not a mesh "
                                                                    r"trimesh can read)"),
    (lambda p, s: open_sphere(s).export(p), r"ball\.obj: not watertight: trimesh reports is_watertight = False, 3 "
                                            r"edge\(s\) on one face only and 0 on more than two; fix the mesh, or set "
                                            r"scene\.repair = true"),
    (lambda p, s: trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 1]]).export(p),
     r"ball\.obj: has no volume \(trimesh reports volume 0"),
])
def test_bad_meshes_are_refused_in_one_line_naming_the_file(tmp_path, icosphere, make, pattern):
    path = tmp_path / "ball.obj"
    if make:
        make(path, icosphere)
    with pytest.raises(MeshError, match=pattern) as e:
        load_mesh(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_repair_closes_a_small_hole_and_says_so(tmp_path, icosphere):
    path = tmp_path / "ball.obj"
    open_sphere(icosphere).export(path)
    tri, notes = load_mesh(path, repair=True)
    assert len(tri) == len(icosphere.faces) and len(notes) == 1
    assert notes[0].startswith(f"{path}: repaired with trimesh's fill_holes (it reported is_watertight = False, 3")
    x_repaired = shapes.sample(shapes.solid(path, repair=True), 16, 1)[0]
    whole = tmp_path / "whole.obj"
    icosphere.export(whole)
    assert abs(len(x_repaired) - len(shapes.sample(shapes.solid(whole), 16, 1)[0])) <= 2


def test_repair_refuses_a_mesh_it_cannot_close(tmp_path, icosphere):
    path = tmp_path / "ball.obj"
    open_sphere(icosphere, missing=len(icosphere.faces) // 2).export(path)  # half a sphere: one big hole
    with pytest.raises(MeshError, match=r"not watertight, and scene\.repair could not close it: trimesh reports "
                                         r"is_watertight = False, \d+ edge\(s\) on one face only .* after fill_holes"):
        load_mesh(path, repair=True)
