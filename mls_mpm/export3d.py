"""The 3D run's sequences for Blender and Houdini: particles/frame_NNNNN.ply and meshes/frame_NNNNN.ply.

Both are binary (little-endian) PLY files written with plyfile, each atomically (frames.atomic_save), and both
are in domain coordinates (the unit cube, y up, the simulation's axes).

- particles: one vertex per particle with `x y z` (float32), `red green blue` (uchar: the particle's colour)
  and `density` (float32): the node masses splatted by P2G (eq 15) and gathered back by the B-spline (G2P) over
  the cell volume dx^3 (field3d.MassField.density_at): the rest density deep inside a body at rest, more where
  it is compressed or overlaps, about half of it at a free surface. It needs no F and counts every particle
  that is near, of whichever part of the body.
- meshes: the surface m(x) = ISO_LEVEL * rest node mass (density * dx^3) of the node masses, interpolated
  linearly between nodes, by marching cubes (scikit-image, Lewiner's topology-consistent variant), with
  `vertex_indices` triangles wound counter-clockwise seen from outside (normals outward) and vertex colours
  `red green blue` (uchar) of the colour field c(x) / m(x) (eq 12) at each vertex. ISO_LEVEL = 1/2 is the edge
  of a B-spline-smoothed body (its contour in the 2D renderer's target outline too): the enclosed volume is
  the body's volume at rest density. The grid is padded with one empty node on every side first, so a body
  touching the grid's edge is closed there too: every mesh is watertight (each edge shared by exactly two
  triangles) unless the field itself is degenerate exactly at the level.
"""
import re

import numpy as np
from plyfile import PlyData, PlyElement

from .frames import atomic_save

PLY_NAME = "frame_{:05d}.ply"
PLY_RE = re.compile(r"^frame_(\d{5,})\.ply$")
PARTICLES_DIR = "particles"
MESHES_DIR = "meshes"
ISO_LEVEL = 0.5  # the mesh's level of m(x) / (density * dx^3)
# The 3D preview's modes (render3d.py), named here, in a module without Taichi, so that the command line lists
# them without loading Taichi; the 2D modes are scene_keys.RENDER_MODES.
MODES_3D = ("surface", "volume", "particles")


def colors_u8(colors):
    """RGB floats in [0, 1] (or uint8) to uint8 (P, 3), rounded."""
    colors = np.asarray(colors)
    if colors.dtype == np.uint8:
        return colors
    return np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)


def _vertices(x, colors, extra=()):
    """A PLY vertex element: x y z float32, red green blue uchar, then the (name, float array) pairs extra."""
    x = np.asarray(x, np.float64).reshape(-1, 3)
    rgb = colors_u8(colors).reshape(-1, 3)
    dtype = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    dtype += [(name, "<f4") for name, _ in extra]
    v = np.empty(len(x), dtype=dtype)
    for k, name in enumerate("xyz"):
        v[name] = x[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        v[name] = rgb[:, k]
    for name, values in extra:
        v[name] = values
    return PlyElement.describe(v, "vertex")


def _write(path, elements):
    return atomic_save(path, lambda tmp: PlyData(elements, text=False, byte_order="<").write(str(tmp)))


def write_particles(frame, path):
    """Write particles/frame_NNNNN.ply from frame = (x (P, 3), colors (P, 3), density (P,)). Returns path."""
    x, colors, density = frame
    return _write(path, [_vertices(x, colors, [("density", np.asarray(density, np.float64))])])


def surface(field, level=ISO_LEVEL):
    """(vertices (V, 3) in domain coordinates, triangles (T, 3) int32, colours (V, 3) floats or None) of the
    iso surface field.m / field.rest = level (field3d.MassField); empty arrays where no node reaches level."""
    from skimage import measure

    t = np.pad(field.t, 1)  # one empty node around the grid: surfaces close at its edges
    if not t.max() > level:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32), None if field.c is None else np.zeros((0, 3))
    dx = 1.0 / field.n_grid
    verts, faces, _, _ = measure.marching_cubes(t, level, spacing=(dx, dx, dx), gradient_direction="descent",
                                                allow_degenerate=False)
    verts = verts - dx  # padded node 1 is node 0, at x = 0
    faces = faces[:, ::-1].astype(np.int32)  # skimage winds them clockwise seen along its descent normals
    return verts, faces, None if field.c is None else field.colors_at(verts)


def write_mesh(mesh, path):
    """Write meshes/frame_NNNNN.ply from mesh = (vertices, triangles, colours or None: grey). Returns path."""
    verts, faces, colors = mesh
    if colors is None:
        colors = np.full((len(verts), 3), 0.8)
    tri = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
    tri["vertex_indices"] = faces
    return _write(path, [_vertices(verts, colors), PlyElement.describe(tri, "face")])


def read_ply(path):
    """{element name: structured array} of a PLY file (for tests and tools)."""
    data = PlyData.read(str(path))
    return {el.name: el.data for el in data.elements}
