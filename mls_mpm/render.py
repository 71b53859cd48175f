"""The Renderer: frames of a run as MPM mass renderings (thesis 7.1), grid color fields (7.5, Figs 7-8) or
particles (Fig 3), with the body's and the target's outlines.

A `Renderer` is built once per run; it owns its fields and renders one frame at a time from numpy arrays. A mass
or color frame is one kernel launch painting the Renderer's white image field (P2G and the two sampling passes
of `sampling`, then `colormap`'s shading), copied out as the frame; outlines are drawn over it by `contour`.

Images are uint8 (size, size, 3) arrays indexed [row, column] (or (size, size, 4) with background="transparent");
the y axis points up like the domain's, so row 0 is y = 1 and column 0 is x = 0. Pixel (r, c) samples the domain point ((c + 1/2) / size, 1 - (r + 1/2) / size).
"""
import numpy as np
import taichi as ti

from .colormap import Thresholds, colormap_kernel, paint_mass, put, shade_mass, to_u8
from .contour import draw_outline
from .kernels import STENCIL
from .sampling import (clear, live_box, mass_field, real_dtype, row_stencil, sample, sample_columns, sample_live,
                       sample_pixel, splat_mass, splat_particle, upload_grid)
from .scene import RENDER_BACKGROUNDS as BACKGROUNDS, RENDER_MODES

BODY_COLOR = (0.85, 0.1, 0.1)  # particles of the body (Fig 3: red)
TARGET_COLOR = (0.0, 0.6, 0.0)  # target positions (Fig 3: green)
TARGET_OUTLINE_COLOR = (0.0, 0.0, 0.0)  # contour of the target mass grid
BODY_OUTLINE_COLOR = (0.35, 0.35, 0.35)  # contour of the body at the "empty" threshold


@ti.kernel
def render_mass(grid_m: ti.template(), line_m: ti.template(), box: ti.template(), pixel_m: ti.template(),
                image: ti.template(), inv_dx: float, scale: float, x: ti.types.ndarray(), m: ti.types.ndarray(),
                n: ti.i32, e: float, low: float, mid: float, high: float):
    """Thesis 7.1 in one launch: P2G, pixel_m = scale * m(x) sampled in two separable passes, and the
    colormap painted over a white image."""
    splat_mass(grid_m, inv_dx, x, m, n)
    sample_columns(grid_m, line_m, inv_dx)
    live_box(grid_m, box, inv_dx, pixel_m.shape[0])
    sample_live(line_m, box, inv_dx, scale, pixel_m)
    paint_mass(pixel_m, image, e, low, mid, high)


@ti.kernel
def render_color(grid_m: ti.template(), grid_c: ti.template(), line_m: ti.template(), line_c: ti.template(),
                 box: ti.template(), pixel_m: ti.template(), image: ti.template(), inv_dx: float, scale: float,
                 x: ti.types.ndarray(), m: ti.types.ndarray(), colors: ti.types.ndarray(), n: ti.i32, e: float,
                 low: float):
    """Thesis 7.5 in one launch: P2G of m_i and the color-mass c_i = sum_p N(x_i - x_p) m_p c_p (eq 12),
    both sampled in two separable passes, and c(x) / m(x) faded to white as the normalised mass
    pixel_m = scale * m(x) falls from `low` to `empty`, painted over a white image."""
    clear(grid_m)
    clear(grid_c)
    ti.loop_config(serialize=True)  # as in splat_mass
    for p in range(n):
        X = ti.Vector([x[p, 0], x[p, 1]])
        splat_particle(grid_m, X, inv_dx, m[p])
        splat_particle(grid_c, X, inv_dx, m[p] * ti.Vector([colors[p, 0], colors[p, 1], colors[p, 2]]))
    sample_columns(grid_m, line_m, inv_dx)
    sample_columns(grid_c, line_c, inv_dx)
    live_box(grid_m, box, inv_dx, pixel_m.shape[0])  # c_i = 0 where m_i = 0
    sample_live(line_m, box, inv_dx, scale, pixel_m)
    for r in range(box[0], box[1] + 1):  # elsewhere pixel_m = 0: white, as the image starts
        J, W = row_stencil(r, line_c, inv_dx)
        for c in range(box[2], box[3] + 1):
            t = pixel_m[r, c]
            if t > e:  # white below
                rgb = ti.math.clamp(sample_pixel(line_c, c, J, W) / (t / scale), 0.0, 1.0)  # m(x) > e * rest > 0
                color = rgb  # the blend below at a = 1
                if t < low:
                    a = (t - e) / (low - e)
                    color = ti.Vector([1.0, 1.0, 1.0]) * (1.0 - a) + rgb * a
                put(image, r, c, to_u8(color))


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
                    put(image, r, c, rgb)
        rc = ti.cast(ti.floor(P), ti.i32)  # a particle thinner than a pixel still shows its own pixel
        if 0 <= rc[0] < size and 0 <= rc[1] < size:
            put(image, rc[1], rc[0], rgb)


@ti.kernel
def fill_white(image: ti.template()):
    for r, c in image:
        image[r, c] = ti.Vector([255, 255, 255], ti.u8)


def estimate_bytes(n_grid, n_particles, size, mode, word, target_res=None):
    """Bytes a Renderer allocates, known before it is built: its fields and buffers (those of `__init__`, and
    those of the target grid of resolution target_res that `_target_field` adds), plus the copy of each frame
    `render` returns. word: bytes of a float (8 for f64, 4 for f32)."""
    n, s, channels = n_grid, size, 4 if mode == "color" else 1  # color mode: m_i and c_i
    fields = word * (channels * (n * n + n * s) + 2 * s * s) + 4 * 4 + 3 * s * s  # grids, lines, pixel_m, ink; box; image
    identity = word * 4 * n_particles
    target = word * (2 * target_res ** 2 + target_res * s + s * s) if target_res else 0  # grid, upload, line, field
    return fields + identity + target + 3 * s * s


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
    body_outline: draw the contour m(x) / rest_node_mass = thresholds.empty over the image, the silhouette of
        the body (over particles too).
    target_level: normalised mass level of the target outline (0.5: the edge of a B-spline-smoothed shape).
    line_width: outline width in pixels.
    background: "white", or "transparent": frames gain an alpha channel, 0 on the background and 255 on the
        material (pixels where m(x) / rest_node_mass > thresholds.empty in the mass and color modes) and on
        every pixel drawn in another color than white (particles, dots, outlines). The background keeps its
        white RGB, so a transparent frame composited on white is the white frame, byte for byte.

    Outlines are marching-squares contours of the pixel-sampled field (`cell_segments`: endpoints interpolated
    linearly between pixel centers, saddles resolved by the cell-center average), drawn line_width pixels wide
    with antialiased edges (`stamp_segment`); `contour` returns the segments themselves.
    """

    def __init__(self, n_grid, n_particles, size=512, rest_node_mass=None, mode="mass", thresholds=None,
                 radius=1.5, body_outline=False, target_level=0.5, line_width=1, background="white"):
        if mode not in RENDER_MODES:
            raise ValueError(f"mode = {mode!r}: expected one of {', '.join(RENDER_MODES)}")
        if background not in BACKGROUNDS:
            raise ValueError(f"background = {background!r}: expected one of {', '.join(BACKGROUNDS)}")
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
        self.background = background
        self.inv_dx = float(n_grid)
        self.real = real_dtype()

        n, s = self.n_grid, self.size
        self.grid_m = ti.field(float, shape=(n, n))  # node mass m_i (eq 15)
        self.grid_c = ti.Vector.field(3, float, shape=(n, n)) if mode == "color" else None  # color-mass c_i (eq 12)
        self.line_m = ti.field(float, shape=(n, s))  # [j, column]: m along grid line y = j dx at each column's x
        self.line_c = ti.Vector.field(3, float, shape=(n, s)) if mode == "color" else None  # the same for c
        self.box = ti.field(ti.i32, shape=4)  # pixel rows and columns reached by mass (`live_box`)
        self.pixel_m = ti.field(float, shape=(s, s))  # m(x) / rest_node_mass at each pixel center, [row, column]
        self.image = ti.Vector.field(3, ti.u8, shape=(s, s))  # the frame being drawn, RGB bytes [row, column]
        self.ink = ti.field(float, shape=(s, s))  # an outline's coverage of each pixel in [0, 1] (`draw_outline`)
        self._identity = np.tile(np.eye(2, dtype=self.real), (self.n_particles, 1, 1))  # F of plain dots
        self._target = None  # (res, grid, line, pixel field, the array uploaded), made for the first target grid

    # -- one frame ---------------------------------------------------------------------------------------
    def render(self, x, m_p, colors=None, F=None, target_x=None, target_outline=None):
        """One frame as uint8 (size, size, 3), or (size, size, 4) with a transparent background.

        x: (N, 2) positions; m_p: particle mass, a number or (N,); colors: (N, 3) RGB in [0, 1] (uint8 is
        read as 0..255), required in "color" mode; F: (N, 2, 2) deformation gradients, drawn as ellipses in
        "particles" mode (dots without); target_x: (M, 2) target positions drawn as green dots over any mode;
        target_outline: a (res, res) target mass grid whose contour at `target_level` is drawn in black.
        """
        x = self._array(x, "x", (-1, 2))
        N = len(x)
        m = self._masses(m_p, N)
        th = self.thresholds
        scale = 1.0 / self.rest_node_mass
        image = self._blank()
        if self.mode == "mass":
            render_mass(self.grid_m, self.line_m, self.box, self.pixel_m, image, self.inv_dx, scale, x, m, N,
                        *th.as_tuple())
        elif self.mode == "color":
            if colors is None:
                raise ValueError("colors: required in color mode, expected shape (N, 3)")
            colors = np.asarray(colors)
            colors = colors / 255.0 if colors.dtype == np.uint8 else colors
            colors = self._array(colors, "colors", (N, 3))
            render_color(self.grid_m, self.grid_c, self.line_m, self.line_c, self.box, self.pixel_m, image,
                         self.inv_dx, scale, x, m, colors, N, th.empty, th.low)
        else:
            if target_x is not None:
                self._dots(image, target_x, TARGET_COLOR)
                target_x = None
            if N:
                F = self._identity_for(N) if F is None else self._array(F, "F", (N, 2, 2))
                draw_particles(image, x, F, N, self.radius, self.size / 8.0, ti.Vector(BODY_COLOR))
            if self.body_outline:
                mass_field(self.grid_m, self.line_m, self.pixel_m, self.inv_dx, scale, x, m, N)
        if self.body_outline:
            self._outline(self.pixel_m, image, th.empty, BODY_OUTLINE_COLOR)
        if target_outline is not None:
            self._outline(self._target_field(target_outline), image, self.target_level, TARGET_OUTLINE_COLOR)
        if target_x is not None:
            self._dots(image, target_x, TARGET_COLOR)
        frame = image.to_numpy()  # each frame gets its own array
        if self.background == "white":
            return frame
        return self._with_alpha(frame, self.pixel_m.to_numpy() > th.empty if self.mode != "particles" else None)

    def render_target(self, target_mass, outline=True):
        """A (res, res) target mass grid in the mass colormap (e.g. the "target" panel of a sheet).

        Entry [i, j] is the node at (i / res, j / res); it is normalised by the rest node mass of its own
        grid, rest_node_mass * (n_grid / res)^2.
        """
        field = self._target_field(target_mass)
        image = self._blank()
        shade_mass(field, image, *self.thresholds.as_tuple())
        if outline:
            self._outline(field, image, self.target_level, TARGET_OUTLINE_COLOR)
        return image.to_numpy()

    def colormap(self, t):
        """(path positions (K,), uint8 colors (K, 3)) of normalised masses t (K,) through the kernels' colormap."""
        t = np.ascontiguousarray(np.ravel(t), dtype=self.real)
        s = np.zeros_like(t)
        rgb = np.zeros((len(t), 3), dtype=np.uint8)
        if len(t):
            colormap_kernel(t, s, rgb, *self.thresholds.as_tuple())
        return s, rgb

    # -- helpers -----------------------------------------------------------------------------------------
    @staticmethod
    def _with_alpha(frame, material=None):
        """frame (H, W, 3) with an alpha channel: 255 where material (a bool (H, W) mask, or None) or where the
        pixel is not white, 0 elsewhere."""
        opaque = np.any(frame != 255, axis=2)
        if material is not None:
            opaque |= material
        return np.concatenate([frame, np.where(opaque, 255, 0).astype(np.uint8)[..., None]], axis=2)

    def _blank(self):
        """The image field, white. The frame kernels draw into this field rather than into a numpy array: on
        a GPU Taichi does not upload an array that a kernel only writes, so a white array would not stay white."""
        fill_white(self.image)
        return self.image

    def _outline(self, field, image, level, color):
        draw_outline(field, self.ink, image, level, float(self.line_width), ti.Vector(color))

    def _dots(self, image, points, color):
        points = self._array(points, "target_x", (-1, 2))
        if len(points):
            draw_particles(image, points, self._identity_for(len(points)), len(points), self.radius,
                           self.size / 8.0, ti.Vector(color))

    def _target_field(self, target):
        """The normalised, pixel-sampled field of a target mass grid; recomputed only when the grid changes."""
        target = np.asarray(target)
        if target.ndim != 2 or target.shape[0] != target.shape[1] or target.shape[0] < STENCIL:
            raise ValueError(f"target mass grid: expected shape (res, res) with res >= {STENCIL}, got {target.shape}")
        res = target.shape[0]
        if self._target is None or self._target[0] != res:
            self._target = (res, ti.field(float, shape=(res, res)), ti.field(float, shape=(res, self.size)),
                            ti.field(float, shape=(self.size, self.size)), None)
        _, grid, line, field, uploaded = self._target
        if uploaded is None or uploaded.shape != target.shape or not np.array_equal(uploaded, target):
            values = self._array(target, "target mass grid", (res, res))
            upload_grid(grid, values)
            rest = self.rest_node_mass * (self.n_grid / res) ** 2  # density * (1 / res)^2
            sample(grid, line, float(res), 1.0 / rest, field)
            self._target = (res, grid, line, field, values.copy())
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
