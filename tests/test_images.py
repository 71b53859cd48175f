"""Images -> particles and grids (mls_mpm/images.py): formats, sampling counts, colors, fit, splatting."""
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mls_mpm import images
from mls_mpm.images import (MAX_PIXELS, ImageError, bspline, check_image, default_region, fit, load_image, material,
                            particle_bound, sample_particles, splat_grid)


def rgba(mask, color=(0.0, 0.0, 0.0)):
    """An RGBA array: color where mask, opaque white elsewhere."""
    out = np.ones(mask.shape + (4,))
    out[mask, :3] = color
    return out


def disk_mask(size, r):
    yy, xx = np.mgrid[:size, :size] + 0.5
    return (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < r ** 2


# ---- load_image --------------------------------------------------------------------------------------------

@pytest.fixture
def disk_u8():
    return np.where(disk_mask(32, 10), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("mode", ["L", "1", "P", "RGB", "RGBA", "LA", "I;16"])
def test_formats_accepted_and_agree(tmp_path, disk_u8, mode):
    """Palette, bilevel, grayscale (+alpha), 16-bit, RGB and RGBA PNGs give the same material mask."""
    gray = Image.fromarray(disk_u8, "L")
    if mode == "I;16":
        img = Image.fromarray(disk_u8.astype(np.uint16) * 257)  # 16-bit gray
        assert img.mode.startswith("I;16")
    elif mode == "P":
        img = gray.convert("RGB").convert("P", palette=Image.Palette.ADAPTIVE, colors=4)
    else:
        img = gray.convert(mode)
    path = tmp_path / f"disk_{mode.replace(';', '')}.png"
    img.save(path)
    a = load_image(path)
    assert a.shape == (32, 32, 4) and a.dtype == np.float64
    assert a.min() >= 0.0 and a.max() <= 1.0
    np.testing.assert_array_equal(material(a), disk_u8 == 0)


def test_16bit_keeps_precision(tmp_path):
    """A 16-bit gray value 32768 reads as 0.5, not clipped to 8 bits."""
    path = tmp_path / "g16.png"
    Image.fromarray(np.full((4, 4), 32768, np.uint16)).save(path)
    np.testing.assert_allclose(load_image(path)[..., :3], 32768 / 65535)


def test_transparent_and_white_are_not_material():
    a = np.zeros((1, 4, 4))
    a[0, 0] = (0, 0, 0, 1.0)  # black opaque: material
    a[0, 1] = (0, 0, 0, 0.4)  # black but transparent
    a[0, 2] = (0.95, 0.95, 0.95, 1.0)  # white
    a[0, 3] = (0.95, 0.95, 0.5, 1.0)  # yellow: one channel not white
    assert material(a).tolist() == [[True, False, False, True]]


def test_missing_file_refused(tmp_path):
    with pytest.raises(ImageError) as e:
        load_image(tmp_path / "nope.png")
    assert "nope.png" in str(e.value) and "no such image file" in str(e.value) and "\n" not in str(e.value)


def test_not_an_image_refused(tmp_path):
    path = tmp_path / "text.png"
    path.write_text("not an image\nat all\n")
    with pytest.raises(ImageError) as e:
        load_image(path)
    assert "text.png" in str(e.value) and "not an image" in str(e.value) and "\n" not in str(e.value)


# ---- sample_particles --------------------------------------------------------------------------------------

ALIGNED = (8 / 32, 8 / 32, 16 / 32, 16 / 32)  # exactly 8 x 8 cells of a 32 grid


@pytest.mark.parametrize("ppc", [1, 3, 4, 9, 16])
def test_full_square_gives_ppc_per_cell(ppc):
    """A full-material image fitted onto k = 64 whole cells gives exactly k * ppc particles, ppc in each cell."""
    x, c = sample_particles(rgba(np.ones((16, 16), bool)), 32, ppc, region=ALIGNED)
    assert x.shape == (64 * ppc, 2) and c.shape == (64 * ppc, 3)
    cells = np.floor(x * 32).astype(int)
    _, counts = np.unique(cells, axis=0, return_counts=True)
    assert len(counts) == 64 and np.all(counts == ppc)
    assert np.all((x >= 0.25) & (x <= 0.5))


def test_disk_count_matches_area():
    """~ppc particles per material cell: count / (area / dx^2 * ppc) within 3%."""
    n_grid, ppc = 32, 16
    x, _ = sample_particles(rgba(disk_mask(64, 28)), n_grid, ppc, region=(0.25, 0.25, 0.75, 0.75))
    area = np.pi * (28 / 64 * 0.5) ** 2
    assert abs(len(x) / (area * n_grid ** 2 * ppc) - 1) < 0.03


def test_lattice_is_jittered_but_stratified():
    """With a square ppc each particle stays in its own sub-cell, but positions are not the plain lattice."""
    x, _ = sample_particles(rgba(np.ones((16, 16), bool)), 32, 4, region=ALIGNED, seed=3)
    sub = np.floor(x * 64).astype(int)  # 2 x 2 sub-cells per cell
    assert len(np.unique(sub, axis=0)) == len(x)
    frac = x * 64 - sub
    assert np.all((frac >= 0.25) & (frac <= 0.75)) and np.std(frac) > 0.05


def test_deterministic_for_a_seed():
    img = rgba(disk_mask(40, 15))
    a, _ = sample_particles(img, 32, 4, seed=7)
    b, _ = sample_particles(img, 32, 4, seed=7)
    c, _ = sample_particles(img, 32, 4, seed=8)
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_colors_come_from_pixels():
    """Left half red, right half blue: particles left of the centre are red, right of it blue."""
    img = np.ones((20, 20, 4))
    img[:, :10, :3] = (1.0, 0.0, 0.0)
    img[:, 10:, :3] = (0.0, 0.0, 1.0)
    x, c = sample_particles(img, 32, 4, region=ALIGNED)
    left = x[:, 0] < 0.375
    assert left.any() and (~left).any()
    np.testing.assert_array_equal(c[left], np.tile([1.0, 0.0, 0.0], (left.sum(), 1)))
    np.testing.assert_array_equal(c[~left], np.tile([0.0, 0.0, 1.0], ((~left).sum(), 1)))


def test_fit_keeps_aspect_and_y_up():
    """A 20 x 40 (H x W) image whose top half is material lands in the upper half of its centred box."""
    mask = np.zeros((20, 40), bool)
    mask[:10] = True  # image rows 0..9: the top
    region = (0.1, 0.1, 0.9, 0.9)
    ox, oy, s = fit(mask.shape, region)
    assert s == pytest.approx(0.02) and (ox, oy) == pytest.approx((0.1, 0.3))  # 0.8 wide, 0.4 high, centred
    x, _ = sample_particles(rgba(mask), 64, 4, region=region)
    assert x[:, 1].min() >= 0.5 - 1e-12 and x[:, 1].max() <= 0.7 + 1e-12
    assert x[:, 0].min() < 0.1 + 1 / 64 and x[:, 0].max() > 0.9 - 1 / 64


def test_default_region_keeps_a_margin_beyond_the_walls():
    assert default_region(32, 3) == pytest.approx((5 / 32, 5 / 32, 27 / 32, 27 / 32))
    x, _ = sample_particles(rgba(np.ones((8, 8), bool)), 32, 4, bound=3)
    assert x.min() >= 5 / 32 and x.max() <= 27 / 32


@pytest.mark.parametrize("img", [np.ones((8, 8, 4)), np.zeros((8, 8, 4))], ids=["white", "transparent"])
def test_no_material_refused(img):
    with pytest.raises(ImageError, match="no material"):
        sample_particles(img, 32, 4)


def test_material_too_small_for_any_particle_refused():
    mask = np.zeros((400, 400), bool)
    mask[0, 0] = True  # one pixel of a 400-pixel image: far smaller than the particle spacing
    with pytest.raises(ImageError, match="no particle landed"):
        sample_particles(rgba(mask), 16, 1, seed=0)


# ---- splat_grid --------------------------------------------------------------------------------------------

def test_bspline_pieces():
    t = np.array([0.0, 0.5, -0.5, 1.0, 1.5, -1.5, 2.0, 2.5])
    want = [2 / 3, 0.0625 - 0.25 + 2 / 3, 0.0625 - 0.25 + 2 / 3, 1 / 6, 0.5 ** 3 / 6, 0.5 ** 3 / 6, 0.0, 0.0]
    np.testing.assert_allclose(bspline(t), want)


def direct_splat(x, m, res, values=None):
    """Reference P2G: loop over particles and their 4 x 4 nodes."""
    C = 1 if values is None else values.shape[1]
    grid = np.zeros((res, res, C))
    for p in range(len(x)):
        base = np.floor(x[p] * res).astype(int) - 1
        for i in range(4):
            for j in range(4):
                I, J = base[0] + i, base[1] + j
                if 0 <= I < res and 0 <= J < res:
                    t = x[p] * res - np.array([I, J])
                    w = bspline(t[0]) * bspline(t[1])
                    grid[I, J] += w * m[p] * (1.0 if values is None else values[p])
    return grid[..., 0] if values is None else grid


def test_splat_matches_direct_loop():
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 1.0, (7, 2))  # some near the edges, where nodes are dropped
    x[0] = (0.001, 0.999)
    m = rng.uniform(0.5, 2.0, 7)
    col = rng.uniform(0, 1, (7, 3))
    np.testing.assert_allclose(splat_grid(x, m, 16), direct_splat(x, m, 16), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(splat_grid(x, m, 16, col), direct_splat(x, m, 16, col), rtol=1e-13, atol=1e-15)
    assert splat_grid(x, m, 16, col).shape == (16, 16, 3)


def test_splat_conserves_mass_inside_and_drops_outside():
    x = np.array([[0.5, 0.5], [0.3, 0.7]])
    assert splat_grid(x, 2.0, 32).sum() == pytest.approx(4.0, rel=1e-13)  # partition of unity
    edge = splat_grid(np.array([[0.01, 0.5]]), 1.0, 32)  # nodes at i = -1 are dropped
    assert 0.5 < edge.sum() < 1.0


def test_splat_entry_ij_is_node_at_i_dx_j_dx():
    """A particle exactly on node (i, j) puts 4/9 of its mass there (N1(0)^2)."""
    g = splat_grid(np.array([[5 / 16, 9 / 16]]), 1.0, 16)
    assert g[5, 9] == pytest.approx(4 / 9) and g.argmax() == 5 * 16 + 9


# ---- files that are not images, and images too large --------------------------------------------------------

def png_header(path, width, height):
    """A PNG whose header claims width x height 8-bit gray pixels, followed by no pixel data."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) +
                     chunk(b"IEND", b""))
    return path


@pytest.mark.parametrize("width, height", [(100000, 100000), (20000, 20000), (MAX_PIXELS // 1000 + 1, 1000)])
@pytest.mark.parametrize("read", [load_image, check_image])
def test_image_above_the_pixel_limit_refused_from_its_header(tmp_path, width, height, read):
    """Refused before decoding (the file holds no pixel data), naming the file, its size and the limit; sizes
    above Pillow's own decompression-bomb limit (2 x 89 megapixels) included."""
    path = png_header(tmp_path / "huge.png", width, height)
    with pytest.raises(ImageError) as e:
        read(path)
    message = str(e.value)
    assert message == (f"{path}: the image is {width} x {height} = {width * height / 1e6:.4g} megapixels, above the "
                       f"limit of 50 megapixels (images.MAX_PIXELS); expected a smaller image")
    assert Image.MAX_IMAGE_PIXELS is not None  # Pillow's own limit is back in place


def test_image_at_the_pixel_limit_is_read_to_its_pixels(tmp_path):
    """A header at exactly MAX_PIXELS passes the size check; its missing pixel data is then what is refused."""
    path = png_header(tmp_path / "big.png", MAX_PIXELS // 1000, 1000)
    with pytest.raises(ImageError, match=r"big\.png: not an image Pillow can read \("):
        check_image(path)


@pytest.mark.parametrize("make, what", [
    (lambda tmp: (tmp / "folder.png").mkdir() or tmp / "folder.png", "is a directory; expected an image file"),
    (lambda tmp: Path("/dev/zero"), "is not a regular file (a device, pipe or socket); expected an image file"),
])
def test_directory_or_device_named_for_what_it_is(tmp_path, make, what):
    path = make(tmp_path)
    for read in (load_image, check_image):
        with pytest.raises(ImageError) as e:
            read(path)
        assert str(e.value) == f"{path}: {what}"


def test_check_image_gives_the_size(tmp_path, disk_u8):
    Image.fromarray(disk_u8[:, :20]).save(tmp_path / "d.png")
    assert check_image(tmp_path / "d.png") == (20, 32)


# ---- chunks and the particle bound -------------------------------------------------------------------------

@pytest.mark.parametrize("ppc", [4, 3])
def test_sampling_and_splatting_do_not_depend_on_the_chunk_size(monkeypatch, ppc):
    """Cells (and particles) are processed CHUNK at a time: the same particles, colors and grids, bit for bit,
    whether a chunk holds a few cells or all of them."""
    img = rgba(disk_mask(50, 20), color=(0.2, 0.4, 0.6))
    x, c = sample_particles(img, 64, ppc, seed=5)
    grids = splat_grid(x, 0.5, 40), splat_grid(x, 0.5, 40, c)
    monkeypatch.setattr(images, "CHUNK", 17)
    x2, c2 = sample_particles(img, 64, ppc, seed=5)
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_array_equal(c2, c)
    np.testing.assert_array_equal(splat_grid(x, 0.5, 40), grids[0])
    np.testing.assert_array_equal(splat_grid(x, 0.5, 40, c), grids[1])


@pytest.mark.parametrize("n_grid, ppc, size, r", [(32, 4, 64, 28), (64, 9, 16, 3), (128, 2, 300, 40), (400, 1, 6, 2)])
def test_particle_bound_holds_and_is_close(n_grid, ppc, size, r):
    """particle_bound >= the particles sampled, for images finer and coarser than the grid, and within 1.6 x
    of them for a disk (the bounding box of a disk is 4 / pi of its area, plus the cells its edge cuts)."""
    mask = disk_mask(size, r)
    n = len(sample_particles(rgba(mask), n_grid, ppc)[0])
    bound = particle_bound(mask, n_grid, ppc)
    assert n <= bound <= 1.6 * n, (n, bound)


def test_particle_bound_counts_only_the_material_box():
    """A small shape in the corner of a large white image: bounded by its own cells, not the image's."""
    mask = np.zeros((400, 400), bool)
    mask[:40, :40] = True
    n = len(sample_particles(rgba(mask), 64, 4)[0])
    assert n <= particle_bound(mask, 64, 4) <= 2 * n  # the image's own cells would give 95 n
    assert particle_bound(np.zeros((8, 8), bool), 64, 4) == 0


# ---- scenes/make_images.py ---------------------------------------------------------------------------------

def test_make_images_reproduces_the_shipped_images(tmp_path, monkeypatch):
    """The generator writes every shipped image byte for byte, the shape pairs of `bench quality` in pairs/
    included, each readable by all, and no temp file."""
    root = Path(__file__).resolve().parents[1]
    monkeypatch.syspath_prepend(str(root / "scenes"))
    import make_images

    make_images.main(tmp_path)
    written = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    shipped = root / "scenes" / "images"
    pngs = [*shipped.glob("*.png"), *shipped.glob("pairs/*.png")]
    assert written == sorted(str(p.relative_to(shipped)) for p in pngs)
    assert sum(name.startswith("pairs/") for name in written) >= 28
    for name in written:
        assert (tmp_path / name).read_bytes() == (shipped / name).read_bytes(), name
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o644, name
