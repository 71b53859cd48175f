"""Plots drawn with Pillow: a box of axes mapping data to pixels, decade and 1-2-5 ticks, and anchored text.

Text is placed from its measured bounding box, so an anchor ("rm": right-middle, "mt": middle-top) means the
same with any font: Pillow's bitmap default font (what `ImageFont.load_default()` gives without FreeType)
ignores the `anchor=` argument of `ImageDraw.text`. Log axes take log10 values. Used by frames.loss_plot, the
scaling plot (bench/scaling.py) and the tradeoff scatter (bench/tradeoff.py).
"""
import math

from PIL import ImageFont

BLACK = (0, 0, 0)


def font():
    """Pillow's default font (FreeType when present, else a bitmap font)."""
    return ImageFont.load_default()


def text(draw, xy, s, font, anchor="lt", fill=BLACK):
    """Draw s with its bounding box anchored at xy: anchor[0] in l/m/r (left, middle, right), anchor[1] in
    t/m/b (top, middle, bottom; d is the same as b)."""
    left, top, right, bottom = draw.textbbox((0, 0), s, font=font)
    w, h = right - left, bottom - top
    x, y = xy
    x -= {"l": 0, "m": w / 2, "r": w}[anchor[0]]
    y -= {"t": 0, "m": h / 2, "d": h, "b": h}[anchor[1]]
    draw.text((x - left, y - top), s, fill=fill, font=font)


def nice_step(raw):
    """The smallest integer step of the form 1, 2, 5 x 10^k that is >= raw."""
    raw = max(raw, 1.0)
    e = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 5, 10):
        if m * e >= raw:
            return int(m * e)
    return int(10 * e)


def linear_ticks(hi, count=8):
    """Integer ticks 0, s, 2s, ... <= hi at a 1-2-5 step s giving at most about `count` ticks."""
    step = nice_step(hi / count)
    return list(range(0, int(math.floor(hi)) + 1, step))


def decade_ticks(lo, hi, mults=(1,)):
    """(log10 value, label) for m x 10^e, e from lo to hi (whole decades), m in mults, up to 10^hi:
    labels "1e-3", "2e-3", "5e-3"."""
    return [(math.log10(m) + e, f"{m}e{e}") for e in range(lo, hi + 1) for m in mults
            if math.log10(m) + e <= hi + 1e-12]


def log_125_ticks(lo, hi):
    """(log10 value, label) for 1, 2, 5 x 10^e within [lo, hi] (log10 values): labels "0.5", "1", "20"."""
    return [(e + math.log10(m), f"{m * 10 ** e:g}") for e in range(math.floor(lo), math.ceil(hi) + 1)
            for m in (1, 2, 5) if lo <= e + math.log10(m) <= hi]


class Axes:
    """A plot box `width` x `height` pixels with its top-left corner at (left, top); x in x_range runs left to
    right, y in y_range bottom to top."""

    def __init__(self, left, top, width, height, x_range, y_range):
        self.left, self.top, self.width, self.height = left, top, width, height
        self.right, self.bottom = left + width, top + height
        (self.x0, self.x1), (self.y0, self.y1) = x_range, y_range

    def px(self, x):
        return self.left + self.width * (x - self.x0) / (self.x1 - self.x0)

    def py(self, y):
        return self.top + self.height * (self.y1 - y) / (self.y1 - self.y0)

    def pt(self, x, y):
        return self.px(x), self.py(y)

    def frame(self, draw):
        draw.rectangle([self.left, self.top, self.right, self.bottom], outline=BLACK)

    def y_tick(self, draw, y, label, font, tick=5, gap=3, grid=None):
        """A tick mark `tick` pixels left of the box at height y, a grid line across it (grid: its colour) and
        the label right-aligned `gap` pixels left of the tick."""
        py = self.py(y)
        if tick:
            draw.line([(self.left - tick, py), (self.left, py)], fill=BLACK)
        if grid:
            draw.line([(self.left + 1, py), (self.right, py)], fill=grid)
        text(draw, (self.left - tick - gap, py), label, font, anchor="rm")

    def x_tick(self, draw, x, label, font, tick=5, gap=3):
        """A tick mark `tick` pixels below the box at x and the label centred `gap` pixels below it."""
        px = self.px(x)
        if tick:
            draw.line([(px, self.bottom), (px, self.bottom + tick)], fill=BLACK)
        text(draw, (px, self.bottom + tick + gap), label, font, anchor="mt")
