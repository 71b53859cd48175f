"""The plotting helper (mls_mpm/plot.py) and the three plots drawn with it: the loss plot (frames.loss_plot,
byte for byte what it drew before the helper existed), the scaling plot and the tradeoff scatter.

tests/data/loss_plot_few.png and loss_plot_many.png were written by frames.loss_plot before it used plot.py,
for the loss lists below; loss.png of a run must not change when the plotting code is reorganised.
"""
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFont

from mls_mpm import plot
from mls_mpm.bench.scaling import plot_scaling
from mls_mpm.bench.tradeoff import scatter
from mls_mpm.frames import loss_plot

DATA = Path(__file__).resolve().parent / "data"
# within two decades (minor 2x and 5x ticks, a dot at every point); a NaN and a zero are left out of the curve
FEW = [3.2e-2, 2.1e-2, 1.5e-2, float("nan"), 9.7e-3, 7.0e-3, 0.0, 5.6e-3, 4.9e-3, 4.6e-3]
# 137 points over five decades (decade ticks only, one dot at the end), another size and title
MANY = list(2.0 * np.exp(-np.arange(137) / 12.0))


@pytest.mark.parametrize("name, losses, kwargs", [
    ("loss_plot_few.png", FEW, {}),
    ("loss_plot_many.png", MANY, {"size": (320, 200), "title": "round 2"}),
])
def test_loss_plot_bytes_unchanged(tmp_path, name, losses, kwargs):
    path = loss_plot(losses, tmp_path / name, **kwargs)
    assert path.read_bytes() == (DATA / name).read_bytes()


# Pillow's bitmap font (what load_default gives without FreeType) ignores ImageDraw.text's anchor=
FONTS = {"freetype": ImageFont.load_default, "bitmap": ImageFont.load_default_imagefont}


def ink(image, box=None):
    """(left, top, right, bottom) of the dark pixels of image (a path or PIL image) within box, or None."""
    a = np.asarray(Image.open(image).convert("L") if isinstance(image, Path) else image.convert("L")) < 128
    x0, y0, x1, y1 = box or (0, 0, a.shape[1], a.shape[0])
    ys, xs = np.nonzero(a[y0:y1, x0:x1])
    return None if not len(xs) else (x0 + xs.min(), y0 + ys.min(), x0 + xs.max(), y0 + ys.max())


@pytest.mark.parametrize("font", FONTS)
@pytest.mark.parametrize("anchor", ["lt", "mm", "rm", "mt", "md", "lm", "rb"])
def test_text_is_anchored_with_either_font(font, anchor):
    """The ink of the text sits on the anchor point: its left/centre/right edge at x, top/middle/bottom at y
    (within 2 pixels: a bitmap glyph cell has blank rows above the ink)."""
    image = Image.new("RGB", (200, 100), "white")
    plot.text(ImageDraw.Draw(image), (100, 50), "1e-3 Wg", FONTS[font](), anchor=anchor)
    left, top, right, bottom = ink(image)
    x = {"l": left, "m": (left + right) / 2, "r": right}[anchor[0]]
    y = {"t": top, "m": (top + bottom) / 2, "d": bottom, "b": bottom}[anchor[1]]
    assert abs(x - 100) <= 2 and abs(y - 50) <= 2, (left, top, right, bottom)


def test_ticks():
    assert plot.decade_ticks(-3, -1) == [(-3, "1e-3"), (-2, "1e-2"), (-1, "1e-1")]
    minor = plot.decade_ticks(-3, -2, (1, 2, 5))
    assert [label for _, label in minor] == ["1e-3", "2e-3", "5e-3", "1e-2"]  # nothing above the top decade
    assert [v for v, _ in minor] == pytest.approx([-3, -3 + np.log10(2), -3 + np.log10(5), -2])
    assert [label for _, label in plot.log_125_ticks(np.log10(0.3), np.log10(60))] == ["0.5", "1", "2", "5", "10",
                                                                                         "20", "50"]
    assert plot.linear_ticks(9) == [0, 2, 4, 6, 8] and plot.linear_ticks(136) == list(range(0, 137, 20))
    assert plot.linear_ticks(1) == [0, 1] and plot.nice_step(0.3) == 1 and plot.nice_step(12.5) == 20


def test_axes_map_data_to_the_box():
    axes = plot.Axes(70, 30, 600, 400, (0, 3), (-2, 2))
    assert axes.pt(0, 2) == (70, 30) and axes.pt(3, -2) == (670, 430) and axes.pt(1.5, 0) == (370, 230)


@pytest.fixture(params=list(FONTS))
def default_font(request, monkeypatch):
    """The plots drawn with the FreeType font, then with the bitmap font."""
    monkeypatch.setattr(ImageFont, "load_default", FONTS[request.param])
    return request.param


def tradeoff_rows():
    rows = [("base", 120.0, 0.2), ("ppc=1", 40.0, 0.5), ("stride=5", 300.0, 0.05), ("f32", 90.0, 0.3)]
    return [{"row": n, "wall_seconds": str(t), "loss_ratio": str(q), "status": "ok"} for n, t, q in rows]


def test_scatter_labels_are_anchored(tmp_path, default_font):
    """Title centred over the plot, the x label centred above the bottom edge, the y tick labels right-aligned
    six pixels left of the box: with either font (the bitmap font ignores anchor=)."""
    path = tmp_path / "tradeoff.png"
    rows = tradeoff_rows()
    scatter(rows, [rows[1], rows[3], rows[0], rows[2]], path, "tiny: accuracy against time")
    left, top, pw, ph, W, H = 70, 30, 630, 404, 720, 480
    title = ink(path, (200, 0, W, 14))  # right of the y axis title, which starts at row 16
    assert abs((title[0] + title[2]) / 2 - (left + pw / 2)) <= 2, title
    xlabel = ink(path, (0, H - 20, W, H))
    assert abs((xlabel[0] + xlabel[2]) / 2 - (left + pw / 2)) <= 2 and xlabel[3] <= H - 8, xlabel
    labels = ink(path, (0, top + 2, left, top + ph - 1))  # the y tick labels, left of the frame
    assert labels is not None and left - 8 <= labels[2] <= left - 5, labels


def test_scaling_labels_are_anchored(tmp_path, default_font):
    """Each panel's axis title centred under it, the y tick labels right-aligned 2 pixels left of its tick marks."""
    results = {"particles": [(1024, 0.1, 0.12, 0.5), (4096, 0.4, 0.5, 2.0), (16384, 1.6, 2.0, 8.0)],
               "steps": [(50, 0.3, 0.4, 1.0), (200, 0.3, 0.4, 1.1)],
               "n_grid": [(32, 0.3, 0.3, 1.0), (64, 0.35, 0.4, 1.2), (128, 0.5, 0.6, 1.5)]}
    path = tmp_path / "scaling.png"
    plot_scaling(results, path)
    W, H, pad = 300, 260, 46
    with Image.open(path) as im:
        assert im.size == (3 * W, H)
    for k in range(3):
        title = ink(path, (k * W, H - 20, (k + 1) * W, H))
        assert abs((title[0] + title[2]) / 2 - (k * W + W / 2)) <= 2, (k, title)
        labels = ink(path, (k * W, 22, k * W + pad - 3, H - pad - 1))  # left of the 3-pixel tick marks
        assert labels is not None and k * W + pad - 8 <= labels[2] <= k * W + pad - 5, (k, labels)
