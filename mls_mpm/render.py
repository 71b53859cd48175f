"""Offline renderers: MPM mass rendering (thesis 7.1), grid color fields (7.5, Figs 7-8), particles (Fig 3).

A `Renderer` is built once per run; it owns its fields and renders one frame at a time from numpy arrays.
Pixels sample the fields with the simulation's own cubic B-spline basis (`kernels.stencil`, `kernels.weights`):
m(x) = sum_i N(x - x_i) m_i, the "fragment shader" of thesis 7.1.

Images are uint8 (size, size, 3) arrays indexed [row, column]; the y axis points up like the domain's, so
row 0 is y = 1 and column 0 is x = 0. Pixel (r, c) samples the domain point ((c + 1/2) / size, 1 - (r + 1/2) / size).
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti
from taichi.lang import impl

from .kernels import STENCIL, stencil, weights

MODES = ("mass", "color", "particles")

# The mass colormap's path, in order: zero (or nearly zero) mass, low, medium, high (thesis 7.1).
WHITE = (1.0, 1.0, 1.0)
BLUE = (0.0, 0.0, 1.0)
GREEN = (0.0, 1.0, 0.0)
RED = (1.0, 0.0, 0.0)
PATH = (WHITE, BLUE, GREEN, RED)

BODY_COLOR = (0.85, 0.1, 0.1)  # particles of the body (Fig 3: red)
TARGET_COLOR = (0.0, 0.6, 0.0)  # target positions (Fig 3: green)
TARGET_OUTLINE_COLOR = (0.0, 0.0, 0.0)  # contour of the target mass grid
BODY_OUTLINE_COLOR = (0.35, 0.35, 0.35)  # contour of the body at the "empty" threshold


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
def pixel_center(r, c, size):
    """The domain point sampled by pixel (row r, column c); rows count down from y = 1."""
    return ti.Vector([(ti.cast(c, float) + 0.5) / size, 1.0 - (ti.cast(r, float) + 0.5) / size])


@ti.func
def interpolate(grid: ti.template(), X, inv_dx):
    """sum_i N(X - x_i) g_i over the 4x4 nodes around X (eq 1-2), nodes off the grid dropped."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    acc = grid[0, 0] * 0.0
    for i, j in ti.static(ti.ndrange(STENCIL, STENCIL)):
        I = base + ti.Vector([i, j])
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1]:
            acc += w[i, 0] * w[j, 1] * grid[I]
    return acc


@ti.func
def scatter(grid: ti.template(), X, inv_dx, value):
    """P2G of one particle's value onto the 4x4 nodes around X (eq 15), nodes off the grid dropped."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    for i, j in ti.static(ti.ndrange(STENCIL, STENCIL)):
        I = base + ti.Vector([i, j])
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1]:
            grid[I] += w[i, 0] * w[j, 1] * value


@ti.func
def position_on_path(t, e, low, mid, high):
    """Ti.func twin of `path_position`: piecewise linear, clamped to [0, 3]."""
    s = 0.0
    if t >= high:
        s = 3.0
    elif t >= mid:
        s = 2.0 + (t - mid) / (high - mid)
    elif t >= low:
        s = 1.0 + (t - low) / (mid - low)
    elif t > e:
        s = (t - e) / (low - e)
    return s


@ti.func
def palette(s):
    """Ti.func twin of `path_color`: white, blue, green, red at s = 0, 1, 2, 3, linear in between."""
    white = ti.Vector(WHITE, dt=float)
    blue = ti.Vector(BLUE, dt=float)
    green = ti.Vector(GREEN, dt=float)
    red = ti.Vector(RED, dt=float)
    color = red
    if s < 1.0:
        color = white + (blue - white) * s
    elif s < 2.0:
        color = blue + (green - blue) * (s - 1.0)
    elif s < 3.0:
        color = green + (red - green) * (s - 2.0)
    return color


@ti.func
def to_u8(color):
    """RGB floats in [0, 1] to bytes, rounded."""
    return ti.cast(ti.math.clamp(color, 0.0, 1.0) * 255.0 + 0.5, ti.u8)


@ti.kernel
def p2g_mass(grid_m: ti.template(), inv_dx: float, x: ti.types.ndarray(), m: ti.types.ndarray(), n: ti.i32):
    """m_i = sum_p N(x_i - x_p) m_p (eq 15)."""
    for p in range(n):
        scatter(grid_m, ti.Vector([x[p, 0], x[p, 1]]), inv_dx, m[p])


@ti.kernel
def p2g_color(grid_m: ti.template(), grid_c: ti.template(), inv_dx: float, x: ti.types.ndarray(),
              m: ti.types.ndarray(), c: ti.types.ndarray(), n: ti.i32):
    """m_i as in p2g_mass and the color-mass c_i = sum_p N(x_i - x_p) m_p c_p (eq 12)."""
    for p in range(n):
        X = ti.Vector([x[p, 0], x[p, 1]])
        scatter(grid_m, X, inv_dx, m[p])
        scatter(grid_c, X, inv_dx, m[p] * ti.Vector([c[p, 0], c[p, 1], c[p, 2]]))


@ti.kernel
def sample(grid: ti.template(), inv_dx: float, scale: float, out: ti.template()):
    """out[r, c] = scale * m(x) at every pixel center: the mass field normalised by the rest node mass."""
    size = out.shape[0]
    for r, c in out:
        out[r, c] = scale * interpolate(grid, pixel_center(r, c, size), inv_dx)


@ti.kernel
def shade_mass(pixel_m: ti.template(), image: ti.template(), e: float, low: float, mid: float, high: float):
    """Thesis 7.1: high mass red, medium green, low blue, nearly zero white."""
    for r, c in image:
        image[r, c] = to_u8(palette(position_on_path(pixel_m[r, c], e, low, mid, high)))


@ti.kernel
def shade_color(grid_c: ti.template(), pixel_m: ti.template(), image: ti.template(), inv_dx: float,
                inv_rest: float, e: float, low: float):
    """Thesis 7.5: c(x) / m(x), faded to white as the normalised mass falls from `low` to `empty`."""
    size = image.shape[0]
    for r, c in image:
        t = pixel_m[r, c]
        color = ti.Vector([1.0, 1.0, 1.0])
        if t > e:
            m = t / inv_rest
            rgb = interpolate(grid_c, pixel_center(r, c, size), inv_dx) / m  # m > e * rest > 0 here
            a = ti.min((t - e) / (low - e), 1.0)
            color = color * (1.0 - a) + ti.math.clamp(rgb, 0.0, 1.0) * a
        image[r, c] = to_u8(color)


@ti.kernel
def draw_particles(image: ti.template(), x: ti.types.ndarray(), F: ti.types.ndarray(), n: ti.i32, radius: float,
                   max_extent: float, color: ti.types.vector(3, float)):
    """Paint, for each particle, the image under F of a disc of `radius` pixels around it (Fig 3's ellipses).

    With F = I this is a dot. A pixel is inside when |F^-1 d| <= radius, d its offset in y-up pixels.
    """
    size = image.shape[0]
    rgb = to_u8(color)
    for p in range(n):
        P = ti.Vector([x[p, 0] * size, (1.0 - x[p, 1]) * size])  # (column, row) in continuous pixels
        A = ti.Matrix([[F[p, 0, 0], F[p, 0, 1]], [F[p, 1, 0], F[p, 1, 1]]])
        det = A.determinant()
        if ti.abs(det) < 1e-8:  # a (nearly) singular F has no usable inverse: draw the plain dot
            A = ti.Matrix.identity(float, 2)
            det = 1.0
        A_inv = ti.Matrix([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]]) / det
        hx = ti.min(radius * ti.sqrt(A[0, 0] ** 2 + A[0, 1] ** 2), max_extent)  # half extents of the ellipse
        hy = ti.min(radius * ti.sqrt(A[1, 0] ** 2 + A[1, 1] ** 2), max_extent)
        c0 = ti.max(ti.cast(ti.floor(P[0] - hx), ti.i32), 0)
        c1 = ti.min(ti.cast(ti.floor(P[0] + hx), ti.i32), size - 1)
        r0 = ti.max(ti.cast(ti.floor(P[1] - hy), ti.i32), 0)
        r1 = ti.min(ti.cast(ti.floor(P[1] + hy), ti.i32), size - 1)
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                d = ti.Vector([ti.cast(c, float) + 0.5 - P[0], P[1] - ti.cast(r, float) - 0.5])
                if (A_inv @ d).norm() <= radius:
                    image[r, c] = rgb
        rc = ti.cast(ti.floor(P), ti.i32)  # a particle thinner than a pixel still shows its own pixel
        if 0 <= rc[0] < size and 0 <= rc[1] < size:
            image[rc[1], rc[0]] = rgb


@ti.kernel
def draw_outline(field: ti.template(), image: ti.template(), level: float, width: ti.i32,
                 color: ti.types.vector(3, float)):
    """Pixel-level contour: paint pixels with field >= level that have a pixel below level within `width`."""
    size = image.shape[0]
    rgb = to_u8(color)
    for r, c in field:
        if field[r, c] >= level:
            edge = False
            for dr, dc in ti.ndrange((-width, width + 1), (-width, width + 1)):
                rr, cc = r + dr, c + dc
                if 0 <= rr < size and 0 <= cc < size and ti.abs(dr) + ti.abs(dc) <= width:
                    if field[rr, cc] < level:
                        edge = True
            if edge:
                image[r, c] = rgb


@ti.kernel
def colormap_kernel(t: ti.types.ndarray(), s: ti.types.ndarray(), rgb: ti.types.ndarray(), e: float, low: float,
                    mid: float, high: float):
    """The mass colormap on an array of normalised masses (for tests and legends)."""
    for k in range(t.shape[0]):
        s[k] = position_on_path(t[k], e, low, mid, high)
        color = to_u8(palette(s[k]))
        for d in ti.static(range(3)):
            rgb[k, d] = color[d]


@ti.kernel
def clear_image(image: ti.template()):
    for r, c in image:
        image[r, c] = ti.Vector([255, 255, 255], dt=ti.u8)


@ti.kernel
def upload_grid(grid: ti.template(), values: ti.types.ndarray()):
    for i, j in grid:
        grid[i, j] = values[i, j]


@ti.data_oriented
class Renderer:
    """Renders frames of one run. Fields are allocated once here; `render` is called once per frame.

    n_grid: simulation grid nodes per axis (dx = 1 / n_grid); mass is splatted onto this grid.
    n_particles: the run's particle count; sizes the default per-particle buffers (other counts still work).
    size: output image side in pixels.
    rest_node_mass: mass a node holds inside material at rest density, density * dx^2; it normalises m(x).
    mode: "mass" (thesis 7.1), "color" (7.5) or "particles" (Fig 3).
    thresholds: `Thresholds` (or a 4-tuple) of the mass colormap and the color mode's fade to white.
    radius: particle dot radius in pixels ("particles" mode and target positions).
    body_outline: draw the contour m(x) / rest_node_mass = thresholds.empty over the image.
    target_level: normalised mass level of the target outline (0.5: the edge of a B-spline-smoothed shape).
    line_width: outline width in pixels.
    """

    def __init__(self, n_grid, n_particles, size=512, rest_node_mass=None, mode="mass", thresholds=None,
                 radius=1.5, body_outline=False, target_level=0.5, line_width=1):
        if mode not in MODES:
            raise ValueError(f"mode = {mode!r}: expected one of {', '.join(MODES)}")
        for name, value, least in (("n_grid", n_grid, STENCIL), ("n_particles", n_particles, 0),
                                   ("size", size, 1), ("line_width", line_width, 1)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} = {value!r}: expected an integer >= {least}")
        if rest_node_mass is None or not (np.isfinite(rest_node_mass) and rest_node_mass > 0):
            raise ValueError(f"rest_node_mass = {rest_node_mass!r}: expected a number > 0 (density * dx^2)")
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius = {radius!r}: expected a number of pixels > 0")
        if thresholds is None:
            thresholds = Thresholds()
        elif not isinstance(thresholds, Thresholds):
            thresholds = Thresholds(*thresholds)
        self.n_grid = int(n_grid)
        self.n_particles = int(n_particles)
        self.size = int(size)
        self.rest_node_mass = float(rest_node_mass)
        self.mode = mode
        self.thresholds = thresholds
        self.radius = float(radius)
        self.body_outline = bool(body_outline)
        self.target_level = float(target_level)
        self.line_width = int(line_width)
        self.inv_dx = float(n_grid)
        self.real = np.float64 if impl.current_cfg().default_fp == ti.f64 else np.float32

        n, s = self.n_grid, self.size
        self.grid_m = ti.field(float, shape=(n, n))  # node mass m_i (eq 15)
        self.grid_c = ti.Vector.field(3, float, shape=(n, n)) if mode == "color" else None  # color-mass c_i (eq 12)
        self.pixel_m = ti.field(float, shape=(s, s))  # m(x) / rest_node_mass at each pixel center, [row, column]
        self.image = ti.Vector.field(3, ti.u8, shape=(s, s))  # RGB, row 0 at y = 1
        self._identity = np.tile(np.eye(2, dtype=self.real), (self.n_particles, 1, 1))  # F of plain dots
        self._target = None  # (res, target fields, the array uploaded), allocated on the first target grid

    # -- one frame ---------------------------------------------------------------------------------------
    def render(self, x, m_p, colors=None, F=None, target_x=None, target_outline=None):
        """One frame as uint8 (size, size, 3).

        x: (N, 2) positions; m_p: particle mass, a number or (N,); colors: (N, 3) RGB in [0, 1] (uint8 is
        read as 0..255), required in "color" mode; F: (N, 2, 2) deformation gradients, drawn as ellipses in
        "particles" mode (dots without); target_x: (M, 2) target positions drawn as green dots over any mode;
        target_outline: a (res, res) target mass grid whose contour at `target_level` is drawn in black.
        """
        x = self._array(x, "x", (-1, 2))
        N = len(x)
        m = self._masses(m_p, N)
        th = self.thresholds
        has_field = False
        if self.mode == "mass":
            self._splat(x, m)
            has_field = True
            shade_mass(self.pixel_m, self.image, *th.as_tuple())
        elif self.mode == "color":
            if colors is None:
                raise ValueError("colors: required in color mode, expected shape (N, 3)")
            colors = np.asarray(colors)
            colors = colors / 255.0 if colors.dtype == np.uint8 else colors
            colors = self._array(colors, "colors", (N, 3))
            self.grid_m.fill(0.0)
            self.grid_c.fill(0.0)
            if N:
                p2g_color(self.grid_m, self.grid_c, self.inv_dx, x, m, colors, N)
            sample(self.grid_m, self.inv_dx, 1.0 / self.rest_node_mass, self.pixel_m)
            has_field = True
            shade_color(self.grid_c, self.pixel_m, self.image, self.inv_dx, 1.0 / self.rest_node_mass, th.empty,
                        th.low)
        else:
            clear_image(self.image)
            if target_x is not None:
                self._dots(target_x, TARGET_COLOR)
                target_x = None
            if N:
                F = self._identity_for(N) if F is None else self._array(F, "F", (N, 2, 2))
                draw_particles(self.image, x, F, N, self.radius, self.size / 8.0, ti.Vector(BODY_COLOR))
        if self.body_outline:
            if not has_field:
                self._splat(x, m)
            draw_outline(self.pixel_m, self.image, th.empty, self.line_width, ti.Vector(BODY_OUTLINE_COLOR))
        if target_outline is not None:
            field = self._target_field(target_outline)
            draw_outline(field, self.image, self.target_level, self.line_width, ti.Vector(TARGET_OUTLINE_COLOR))
        if target_x is not None:
            self._dots(target_x, TARGET_COLOR)
        return self.image.to_numpy()

    def render_target(self, target_mass, outline=True):
        """A (res, res) target mass grid in the mass colormap (e.g. the "target" panel of a sheet).

        Entry [i, j] is the node at (i / res, j / res); it is normalised by the rest node mass of its own
        grid, rest_node_mass * (n_grid / res)^2.
        """
        field = self._target_field(target_mass)
        shade_mass(field, self.image, *self.thresholds.as_tuple())
        if outline:
            draw_outline(field, self.image, self.target_level, self.line_width, ti.Vector(TARGET_OUTLINE_COLOR))
        return self.image.to_numpy()

    def colormap(self, t):
        """(path positions (K,), uint8 colors (K, 3)) of normalised masses t (K,) through the kernels' colormap."""
        t = np.ascontiguousarray(np.ravel(t), dtype=self.real)
        s = np.zeros_like(t)
        rgb = np.zeros((len(t), 3), dtype=np.uint8)
        if len(t):
            colormap_kernel(t, s, rgb, *self.thresholds.as_tuple())
        return s, rgb

    # -- helpers -----------------------------------------------------------------------------------------
    def _splat(self, x, m):
        self.grid_m.fill(0.0)
        if len(x):
            p2g_mass(self.grid_m, self.inv_dx, x, m, len(x))
        sample(self.grid_m, self.inv_dx, 1.0 / self.rest_node_mass, self.pixel_m)

    def _dots(self, points, color):
        points = self._array(points, "target_x", (-1, 2))
        if len(points):
            draw_particles(self.image, points, self._identity_for(len(points)), len(points), self.radius,
                           self.size / 8.0, ti.Vector(color))

    def _target_field(self, target):
        """The normalised, pixel-sampled field of a target mass grid; recomputed only when the grid changes."""
        target = np.asarray(target)
        if target.ndim != 2 or target.shape[0] != target.shape[1] or target.shape[0] < STENCIL:
            raise ValueError(f"target mass grid: expected shape (res, res) with res >= {STENCIL}, got {target.shape}")
        res = target.shape[0]
        if self._target is None or self._target[0] != res:
            self._target = (res, ti.field(float, shape=(res, res)), ti.field(float, shape=(self.size, self.size)),
                            None)
        _, grid, field, uploaded = self._target
        if uploaded is None or uploaded.shape != target.shape or not np.array_equal(uploaded, target):
            values = self._array(target, "target mass grid", (res, res))
            upload_grid(grid, values)
            rest = self.rest_node_mass * (self.n_grid / res) ** 2  # density * (1 / res)^2
            sample(grid, float(res), 1.0 / rest, field)
            self._target = (res, grid, field, values.copy())
        return field

    def _identity_for(self, N):
        return self._identity[:N] if N <= len(self._identity) else np.tile(np.eye(2, dtype=self.real), (N, 1, 1))

    def _masses(self, m_p, N):
        m = np.asarray(m_p, dtype=np.float64)
        if m.ndim == 0:
            m = np.full(N, float(m))
        if m.shape != (N,) or not np.all(np.isfinite(m)) or np.any(m < 0):
            raise ValueError(f"m_p: expected a number or an array of shape ({N},) of finite masses >= 0")
        return m.astype(self.real)

    def _array(self, a, name, shape):
        a = np.asarray(a, dtype=np.float64)
        want = tuple(a.shape[0] if k == -1 and a.ndim else k for k in shape)
        if a.shape != want:
            raise ValueError(f"{name}: expected shape {tuple('N' if k == -1 else k for k in shape)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: holds NaN or Inf")
        return np.ascontiguousarray(a, dtype=self.real)
