"""The mass colormap of thesis 7.1: normalised mass t = m(x) / rest_node_mass to white, blue, green, red.

`Thresholds` are the levels of t where each color is reached; `path_position` and `path_color` are the numpy
references of the `position_on_path` and `palette` ti.funcs the frame kernels use. Colors are RGB floats in
[0, 1] until `to_u8` rounds them to the bytes `put` writes into an image field (3 x uint8, [row, column]).
"""
from dataclasses import dataclass

import numpy as np
import taichi as ti

# The colormap's path, in order: zero (or nearly zero) mass, low, medium, high.
WHITE = (1.0, 1.0, 1.0)
BLUE = (0.0, 0.0, 1.0)
GREEN = (0.0, 1.0, 0.0)
RED = (1.0, 0.0, 0.0)
PATH = (WHITE, BLUE, GREEN, RED)


@dataclass(frozen=True)
class Thresholds:
    """Levels of normalised mass t = m(x) / rest_node_mass at which the mass colormap reaches each color.

    t <= empty: white; empty..low: white -> blue; low..mid: blue -> green; mid..high: green -> red;
    t >= high: red (clamped). Material at rest density has t = 1 and renders red. The color mode blends
    c(x) / m(x) from white over the same empty..low band, and the body outline is the contour t = empty.
    """

    empty: float = 0.02
    low: float = 0.25
    mid: float = 0.6
    high: float = 1.0

    def __post_init__(self):
        levels = (self.empty, self.low, self.mid, self.high)
        if not (all(np.isfinite(levels)) and 0.0 <= self.empty < self.low < self.mid < self.high):
            raise ValueError(f"thresholds = {levels}: expected 0 <= empty < low < mid < high")

    def as_tuple(self):
        return (self.empty, self.low, self.mid, self.high)


def path_position(t, thresholds: Thresholds = Thresholds()):
    """Position s in [0, 3] along white -> blue -> green -> red of normalised masses t (numpy reference).

    Non-decreasing in t; the color of t is PATH[floor(s)] blended linearly towards the next color by frac(s).
    """
    levels = np.asarray(thresholds.as_tuple())
    return np.interp(np.asarray(t, dtype=np.float64), levels, np.arange(4.0))


def path_color(s):
    """RGB floats (..., 3) of path positions s in [0, 3] (numpy reference of the `palette` ti.func)."""
    s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 3.0)
    return np.stack([np.interp(s, np.arange(4.0), [c[k] for c in PATH]) for k in range(3)], axis=-1)


@ti.func
def position_on_path(t, e, low, mid, high):
    """Ti.func twin of `path_position`: piecewise linear, clamped to [0, 3].

    t >= high shares the green..red piece, clamped to s = 3 (the same value as a separate branch), so that
    masses fluctuating around `high` inside a body at rest do not flip a branch from pixel to pixel.
    """
    s = 0.0
    if t >= mid:
        s = 2.0 + ti.min((t - mid) / (high - mid), 1.0)
    elif t >= low:
        s = 1.0 + (t - low) / (mid - low)
    elif t > e:
        s = (t - e) / (low - e)
    return s


@ti.func
def palette(s):
    """Ti.func twin of `path_color`: white, blue, green, red at s = 0, 1, 2, 3, linear in between (s <= 3)."""
    white = ti.Vector(WHITE, dt=float)
    blue = ti.Vector(BLUE, dt=float)
    green = ti.Vector(GREEN, dt=float)
    red = ti.Vector(RED, dt=float)
    color = green + (red - green) * (s - 2.0)  # red at s = 3
    if s < 1.0:
        color = white + (blue - white) * s
    elif s < 2.0:
        color = blue + (green - blue) * (s - 1.0)
    return color


@ti.func
def to_u8(color):
    """RGB floats in [0, 1] to bytes, rounded."""
    return ti.cast(ti.math.clamp(color, 0.0, 1.0) * 255.0 + 0.5, ti.u8)


@ti.func
def put(image: ti.template(), r, c, rgb):
    """Write the bytes rgb to pixel (r, c) of the image field (3 x uint8 per pixel, [row, column])."""
    image[r, c] = rgb


@ti.func
def paint_mass(pixel_m: ti.template(), image: ti.template(), e, low, mid, high):
    """The colormap (high mass red, medium green, low blue) painted over a white image where pixel_m > empty
    (below, position_on_path is 0: white, as the image starts)."""
    for r, c in pixel_m:
        t = pixel_m[r, c]
        if t > e:
            put(image, r, c, to_u8(palette(position_on_path(t, e, low, mid, high))))


@ti.kernel
def shade_mass(pixel_m: ti.template(), image: ti.template(), e: float, low: float, mid: float, high: float):
    """The colormap of a sampled field of normalised mass, painted over a white image."""
    paint_mass(pixel_m, image, e, low, mid, high)


@ti.kernel
def colormap_kernel(t: ti.types.ndarray(), s: ti.types.ndarray(), rgb: ti.types.ndarray(), e: float, low: float,
                    mid: float, high: float):
    """The colormap on an array of normalised masses (for tests and legends)."""
    for k in range(t.shape[0]):
        s[k] = position_on_path(t[k], e, low, mid, high)
        color = to_u8(palette(s[k]))
        for d in ti.static(range(3)):
            rgb[k, d] = color[d]
