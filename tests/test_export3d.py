"""3D sequences (mls_mpm/export3d.py, field3d.py): PLY particles and marching-cubes meshes read back, a sphere's
mesh watertight with the sphere's volume, the grid transfers against their definitions. numpy only (no Taichi)."""
import numpy as np
import pytest

from mls_mpm.export3d import ISO_LEVEL, colors_u8, read_ply, surface, write_mesh, write_particles
from mls_mpm.field3d import MassField, gather, mass_field, splat, trilinear
from mls_mpm.images import bspline

N_GRID = 32
DX = 1.0 / N_GRID
DENSITY = 40.0
PPC_AXIS = 2  # 8 particles per cell


def ball(center, radius, colors=None):
    """Particles filling a ball at 8 per cell on a regular lattice, with the rest-density mass."""
    s = (np.arange(N_GRID * PPC_AXIS) + 0.5) * DX / PPC_AXIS
    x = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    x = x[np.linalg.norm(x - center, axis=1) < radius]
    return x, DENSITY * DX ** 3 / PPC_AXIS ** 3


def edges_count(faces):
    """How many triangles share each undirected edge."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def enclosed_volume(verts, faces):
    """Signed volume of a closed triangle mesh (divergence theorem): > 0 when its normals point outward."""
    a, b, c = (verts[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_splat_and_gather_match_the_b_spline_sums():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.3, 0.6, (40, 3))  # every stencil on the 8^3 grid
    m = rng.uniform(0.5, 2.0, 40)
    colors = rng.uniform(0, 1, (40, 3))
    grid_m, grid_c = splat(x, m, 8, colors)
    nodes = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1) / 8.0  # (8, 8, 8, 3)
    N = np.prod(bspline((nodes[None] - x[:, None, None, None]) * 8), axis=-1)  # (P, 8, 8, 8)
    np.testing.assert_allclose(grid_m, np.einsum("p,pijk->ijk", m, N), rtol=1e-12)
    np.testing.assert_allclose(grid_c, np.einsum("p,pc,pijk->ijkc", m, colors, N), rtol=1e-12)
    np.testing.assert_allclose(gather(grid_m, x), np.einsum("ijk,pijk->p", grid_m, N), rtol=1e-12)
    assert grid_m.sum() == pytest.approx(m.sum(), rel=1e-12)  # every stencil on the grid: mass conserved


def test_splat_and_gather_drop_the_nodes_beyond_the_grid():
    rng = np.random.default_rng(1)
    x = rng.uniform(0.0, 1.0, (60, 3))  # stencils that reach past both ends of the 8^3 grid
    m = rng.uniform(0.5, 2.0, 60)
    grid_m, _ = splat(x, m, 8)
    nodes = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1) / 8.0
    N = np.prod(bspline((nodes[None] - x[:, None, None, None]) * 8), axis=-1)  # the nodes that exist only
    np.testing.assert_allclose(grid_m, np.einsum("p,pijk->ijk", m, N), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(gather(grid_m, x), np.einsum("ijk,pijk->p", grid_m, N), rtol=1e-12, atol=1e-15)
    assert grid_m.sum() < m.sum()  # mass whose nodes are off the grid is dropped


def test_trilinear_is_exact_at_nodes_and_linear_between():
    g = np.arange(4 ** 3, dtype=float).reshape(4, 4, 4)  # linear in the index: 16 i + 4 j + k
    pts = np.array([[0.25, 0.5, 0.0], [0.125, 0.3, 0.6]])
    np.testing.assert_allclose(trilinear(g, pts, 4), (pts * 4) @ [16.0, 4.0, 1.0], rtol=1e-12)


def test_density_is_the_rest_density_inside_a_body_at_rest():
    x, m_p = ball((0.5, 0.5, 0.5), 0.3)
    field = mass_field(x, m_p, N_GRID, DENSITY)
    rho = field.density_at(x)
    deep = np.linalg.norm(x - 0.5, axis=1) < 0.3 - 3 * DX
    np.testing.assert_allclose(rho[deep], DENSITY, rtol=2e-4)  # the lattice's B-spline sum
    assert 0.2 * DENSITY < rho.min() < 0.7 * DENSITY  # about half at the surface


def test_particle_ply_reads_back_what_was_written(tmp_path):
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (50, 3))
    colors = rng.uniform(0, 1, (50, 3))
    density = rng.uniform(0, 80, 50)
    path = write_particles((x, colors, density), tmp_path / "frame_00000.ply")
    assert path.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    v = read_ply(path)["vertex"]
    assert v.dtype.names == ("x", "y", "z", "red", "green", "blue", "density")
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), x.astype(np.float32))
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), colors_u8(colors))
    np.testing.assert_array_equal(v["density"], density.astype(np.float32))
    assert colors_u8(np.array([[0.0, 0.5, 1.0]])).tolist() == [[0, 128, 255]]
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.parametrize("center, radius, tol", [((0.5, 0.5, 0.5), 0.25, 0.03), ((0.45, 0.52, 0.5), 0.2, 0.05)])
def test_a_spheres_mesh_is_watertight_with_the_spheres_volume(center, radius, tol):
    """The level-1/2 surface of the B-spline-smoothed ball lies a little inside it (the smoothing rounds a
    curved surface inwards): measured -2.0% of the volume at a radius of 8 cells, -3.9% at 6.4 cells."""
    x, m_p = ball(center, radius)
    verts, faces, colors = surface(mass_field(x, m_p, N_GRID, DENSITY))
    assert colors is None and len(faces) > 100
    assert (edges_count(faces) == 2).all()  # closed, and no edge shared by more than two triangles
    assert len(verts) - len(edges_count(faces)) + len(faces) == 2  # Euler characteristic of a sphere
    sphere = 4.0 / 3.0 * np.pi * radius ** 3
    assert 1 - tol < enclosed_volume(verts, faces) / sphere < 1.0  # > 0: normals outward
    r = np.linalg.norm(verts - center, axis=1)
    assert np.abs(r - radius).max() < 0.6 * DX  # the level 1/2 is the smoothed body's edge


def test_a_body_touching_the_grid_edge_is_closed_there():
    field = MassField(np.zeros((N_GRID,) * 3), None, DENSITY)
    field.m[:10, 8:20, 8:20] = field.rest  # a box of nodes at rest density from the face x = 0
    verts, faces, _ = surface(field)
    assert (edges_count(faces) == 2).all()
    assert verts[:, 0].min() == pytest.approx(-0.5 * DX)  # closed between node 0 and the padding's empty node
    volume = (10 - 0.5 + 0.5) * 12 * 12 * DX ** 3  # level 1/2 half-way between the last full and first empty node
    assert enclosed_volume(verts, faces) == pytest.approx(volume, rel=0.05)


def test_mesh_colors_are_the_particles_and_the_ply_reads_back(tmp_path):
    x, m_p = ball((0.5, 0.5, 0.5), 0.25)
    colors = np.where(x[:, :1] < 0.5, [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])  # left half red, right half blue
    mesh = surface(mass_field(x, m_p, N_GRID, DENSITY, colors))
    verts, faces, vc = mesh
    left, right = verts[:, 0] < 0.5 - 3 * DX, verts[:, 0] > 0.5 + 3 * DX
    np.testing.assert_allclose(vc[left], [[1.0, 0.0, 0.0]] * left.sum(), atol=1e-9)
    np.testing.assert_allclose(vc[right], [[0.0, 0.0, 1.0]] * right.sum(), atol=1e-9)
    data = read_ply(write_mesh(mesh, tmp_path / "frame_00000.ply"))
    v, f = data["vertex"], data["face"]
    np.testing.assert_array_equal(np.stack([v["x"], v["y"], v["z"]], 1), verts.astype(np.float32))
    np.testing.assert_array_equal(np.stack([v["red"], v["green"], v["blue"]], 1), colors_u8(vc))
    np.testing.assert_array_equal(np.stack(f["vertex_indices"]), faces)


def test_a_field_below_the_level_writes_an_empty_mesh(tmp_path):
    x, m_p = ball((0.5, 0.5, 0.5), 0.25)
    field = mass_field(x, m_p * ISO_LEVEL * 0.9, N_GRID, DENSITY)  # too light to reach the level anywhere
    verts, faces, _ = surface(field)
    assert verts.shape == (0, 3) and faces.shape == (0, 3)
    data = read_ply(write_mesh((verts, faces, None), tmp_path / "empty.ply"))
    assert len(data["vertex"]) == 0 and len(data["face"]) == 0
