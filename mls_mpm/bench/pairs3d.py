"""The 3D shape pairs of `mls-mpm bench quality --dim 3`, and the meshes some of them morph.

Each pair names its INITIAL and TARGET as `mls-mpm morph` takes them (shapes.py): built-in solids ("shape:..."),
a colour image of the 2D suite extruded into a slab ("extrude:..."), or a mesh file named by its file name alone
(capsule.obj), one of MESHES: trimesh.creation writes it into the run's <out>/meshes/ (trimesh builds the same
mesh every time; the files are not shipped), so the suite reads meshes the way a user's own are read, in four
formats. Mesh frames are their bounding boxes, each fitted into the region on its own (shapes.py), so a mesh pair's
volumes are those of the fitted shapes; built-in shapes keep their sizes in the unit cube.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..checkpoint import atomic_write

PAIRS_DIR = Path(__file__).resolve().parents[2] / "scenes" / "images" / "pairs"

# What the 3D suite covers; every pair names the one it stands for.
CATEGORIES = ("volume 1/3", "volume 3", "off-centre", "thin", "hole opens", "hole closes", "split", "merge",
              "stretch", "colour")

# file name -> (trimesh.creation function, its arguments): sizes in the mesh's own units
MESHES = {
    "capsule.obj": ("capsule", {"height": 0.5, "radius": 0.15}),
    "ring.ply": ("annulus", {"r_min": 0.2, "r_max": 0.32, "height": 0.1}),
    "ball.obj": ("icosphere", {"subdivisions": 3, "radius": 0.3}),
    "bar.stl": ("box", {"extents": (0.6, 0.2, 0.2)}),
    "cone.off": ("cone", {"radius": 0.3, "height": 0.6}),
    "cyl.ply": ("cylinder", {"radius": 0.15, "height": 0.7}),
    "torus.obj": ("torus", {"major_radius": 0.3, "minor_radius": 0.1}),
}


@dataclass(frozen=True)
class Pair3D:
    name: str
    category: str  # one of CATEGORIES
    tests: str  # what the pair tests, one phrase
    initial_text: str  # a shape text; a bare mesh file name is one of MESHES
    target_text: str

    def inputs(self, meshes: Path) -> tuple[str, str]:
        """INITIAL and TARGET for `mls-mpm morph`, a mesh of MESHES as its path in the folder `meshes`."""
        return tuple(str(Path(meshes) / t) if t in MESHES else t for t in (self.initial_text, self.target_text))

    def images(self) -> list[Path]:
        """The shipped images the pair extrudes (they must exist before anything runs)."""
        return [Path(t[len("extrude:"):].partition("?")[0]) for t in (self.initial_text, self.target_text)
                if t.startswith("extrude:")]


def _extruded(image):
    return f"extrude:{PAIRS_DIR / image}?depth=0.25"


PAIRS = (
    Pair3D("shrink_ball", "volume 1/3", "ball to a ball of 1/3 the volume", "shape:sphere?r=0.3",
           "shape:sphere?r=0.208"),
    Pair3D("grow_box", "volume 3", "cube to a cube of 3x the volume", "shape:box?sx=0.3&sy=0.3&sz=0.3",
           "shape:box?sx=0.433&sy=0.433&sz=0.433"),
    Pair3D("corner_ball", "off-centre", "ball to the same ball in a corner", "shape:sphere?r=0.2",
           "shape:sphere?r=0.2&cx=0.72&cy=0.72&cz=0.72"),
    Pair3D("capsule_to_ring", "thin", "capsule mesh to a flat ring mesh (about 2 cells thick at 24^3)", "capsule.obj",
           "ring.ply"),
    Pair3D("box_to_torus", "hole opens", "cube to a torus of 0.68 its volume", "shape:box", "shape:torus"),
    Pair3D("torus_to_ball", "hole closes", "torus mesh to a ball mesh", "torus.obj", "ball.obj"),
    Pair3D("ball_to_two", "split", "ball to two balls of 0.59 its volume", "shape:sphere", "shape:two_spheres"),
    Pair3D("two_to_bar", "merge", "two balls to one bar joining them", "shape:two_spheres",
           "shape:box?sx=0.9&sy=0.27&sz=0.27"),
    Pair3D("ball_to_bar", "stretch", "ball mesh to a bar mesh (1/4.7 the volume once fitted)", "ball.obj", "bar.stl"),
    Pair3D("cone_to_cylinder", "stretch", "cone mesh to a slim cylinder mesh", "cone.off", "cyl.ply"),
    Pair3D("color_slab", "colour", "extruded red-blue bar to an extruded blue-red disk",
           _extruded("color_bar_to_disk_initial.png"), _extruded("color_bar_to_disk_target.png")),
)
QUICK = ("corner_ball", "box_to_torus", "ball_to_two")  # --quick --dim 3: a move, a hole, a split, at fast


def write_meshes(folder, names=None) -> Path:
    """Write the MESHES named (default: all) into folder (created), each atomically; returns the folder."""
    import trimesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in MESHES if names is None else names:
        make, kwargs = MESHES[name]
        data = getattr(trimesh.creation, make)(**kwargs).export(file_type=Path(name).suffix[1:])
        atomic_write(folder / name, lambda fh: fh.write(data if isinstance(data, bytes) else data.encode()))
    return folder
