"""The headless preview of a 3D run: frames of the mass field seen by a fixed camera, on the CPU, no display.

A small Taichi ray caster of the node grid (field3d.MassField), chosen over an external renderer (Mitsuba 3 and
the like) because it needs no new dependency, draws exactly the field the meshes are cut from, and renders a
512^2 frame in milliseconds on 2 CPU cores (BENCHMARKS.md, "3D outputs per frame").

Camera: orthographic, looking at the domain's centre (1/2, 1/2, 1/2) from the direction VIEW_FROM = (1, 0.8,
1.4) (right, above and in front: the x axis points right, y up, z towards the viewer), y up. The image shows the
whole unit cube: its half-width is that of the cube's projection. Pixel (r, c) is the ray through
centre + u right + v up with u = (2 (c + 1/2) / size - 1) half, v = (1 - 2 (r + 1/2) / size) half.

Each ray sees the normalised mass t(x) = m(x) / (density dx^3) (m interpolated linearly between nodes, as the
meshes of export3d) between its entry and exit of the box of the nodes with mass.

- "surface": the first point where t reaches export3d.ISO_LEVEL, i.e. the mesh's surface, found exactly for the
  interpolant: the ray walks the cells it crosses, and in a cell that can reach the level solves the cubic that t
  is along the ray there (a march by fixed half-cell steps, before, stepped over parts thinner than its step along
  the ray: stripes where a thin or stretched part is seen edge-on, gaps in a sheet). The surface is shaded by a
  Lambert light (AMBIENT + (1 - AMBIENT) max(0, n . LIGHT), n the field's outward normal) and coloured by the
  thesis 7.1 colormap of t BENEATH = 2 cells beneath the surface (red where the body is at rest density and thick,
  green and blue where it is thin or stretched), or, in a colour scene, by c(x) / m(x).
- "volume": front-to-back emission-absorption compositing of samples every half cell with t > thresholds.empty,
  emitting the colormap of t (or c / m) with opacity 1 - exp(-VOLUME_DENSITY t h / dx) over a step h, on white.
- "particles": each particle a shaded sphere of about half the particle spacing (nearest one per pixel, found by
  an atomic minimum of (depth, particle index), so the image does not depend on thread order), red or its colour.

The target's silhouette (the contour, at target_level, of the largest target mass along each ray) is drawn in
black over any mode when a target grid is given (contour.draw_outline, as in 2D).
"""
import numpy as np
import taichi as ti

from .colormap import Thresholds, palette, position_on_path, put, to_u8
from .contour import draw_outline
from .export3d import ISO_LEVEL, MODES_3D
from .render import BODY_COLOR, TARGET_OUTLINE_COLOR, fill_white
from .sampling import real_dtype

VIEW_FROM = (1.0, 0.8, 1.4)  # direction from the domain's centre to the camera
CENTRE = (0.5, 0.5, 0.5)
AMBIENT = 0.35  # share of a surface's colour lit from everywhere
VOLUME_DENSITY = 0.6  # optical depth of one cell of material at rest density (t = 1)
BENEATH = 2  # cells beneath the surface where the surface mode reads t for the colormap
LIGHT_MIX = (0.8, 0.5, -0.3)  # LIGHT = normalised mix of (towards the camera, up, right): from above left
ROOT_STEPS = 8  # bisection steps of a surface hit in its cell, then a chord: within 1/256 of a cell


def camera():
    """(d: unit vector towards the camera, right, up, half-width of the view), numpy, as documented above."""
    d = np.asarray(VIEW_FROM, np.float64)
    d /= np.linalg.norm(d)
    right = np.cross((0.0, 1.0, 0.0), d)
    right /= np.linalg.norm(right)
    up = np.cross(d, right)
    half = 0.5 * max(np.abs(right).sum(), np.abs(up).sum())  # the unit cube's projection, centred
    return d, right, up, half


def project(points, size):
    """(column, row, depth) of domain points (P, 3) in continuous pixel coordinates (pixel (r, c) spans
    [c, c + 1) x [r, r + 1)); depth grows away from the camera."""
    d, right, up, half = camera()
    q = np.asarray(points, np.float64) - CENTRE
    col = (q @ right / half + 1.0) * size / 2
    row = (1.0 - q @ up / half) * size / 2
    return col, row, -(q @ d)


@ti.func
def trilinear_at(grid: ti.template(), p, inv_dx):
    """grid interpolated linearly between nodes at domain point p (node i at i dx); 0 beyond the grid."""
    q = p * inv_dx
    i0 = ti.cast(ti.floor(q), ti.i32)
    f = q - ti.cast(i0, float)
    acc = ti.zero(grid[0, 0, 0])
    for o in ti.static(ti.grouped(ti.ndrange(2, 2, 2))):
        I = i0 + o
        w = 1.0
        for a in ti.static(range(3)):
            w *= f[a] if o[a] == 1 else 1.0 - f[a]
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1] and 0 <= I[2] < grid.shape[2]:
            acc += w * grid[I]
    return acc


@ti.func
def trilinear_grad(grid: ti.template(), p, inv_dx):
    """(value, gradient in index units) of the scalar grid interpolated linearly between nodes at domain point
    p: the gradient of the trilinear interpolant inside p's cell (0 beyond the grid)."""
    q = p * inv_dx
    i0 = ti.cast(ti.floor(q), ti.i32)
    f = q - ti.cast(i0, float)
    value = 0.0
    grad = ti.Vector([0.0, 0.0, 0.0])
    for o in ti.static(ti.grouped(ti.ndrange(2, 2, 2))):
        I = i0 + o
        g = 0.0
        if 0 <= I[0] < grid.shape[0] and 0 <= I[1] < grid.shape[1] and 0 <= I[2] < grid.shape[2]:
            g = grid[I]
        w = ti.Vector([f[a] if o[a] == 1 else 1.0 - f[a] for a in ti.static(range(3))])
        dw = ti.Vector([1.0 if o[a] == 1 else -1.0 for a in ti.static(range(3))])
        value += w[0] * w[1] * w[2] * g
        grad += ti.Vector([dw[0] * w[1] * w[2], w[0] * dw[1] * w[2], w[0] * w[1] * dw[2]]) * g
    return value, grad


@ti.func
def ray(r, c, size, cam: ti.template()):
    """(origin outside the unit cube, direction) of pixel (r, c)'s ray; cam = [d, right, up, (half, 0, 0)]."""
    u = (2.0 * (ti.cast(c, float) + 0.5) / size - 1.0) * cam[3][0]
    v = (1.0 - 2.0 * (ti.cast(r, float) + 0.5) / size) * cam[3][0]
    o = ti.Vector(CENTRE, dt=float) + u * cam[1] + v * cam[2] + 2.0 * cam[0]
    return o, -cam[0]


@ti.func
def box_span(o, dirn, lo, hi):
    """(t0, t1) of the ray o + s dirn inside the box [lo, hi] (t0 > t1: it misses)."""
    t0, t1 = -1e30, 1e30
    for a in ti.static(range(3)):
        inv = 1.0 / dirn[a]  # dirn has no zero component: VIEW_FROM has none
        s0, s1 = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
        t0 = ti.max(t0, ti.min(s0, s1))
        t1 = ti.min(t1, ti.max(s0, s1))
    return t0, t1


@ti.func
def shade_color(t, rgb, colored, e, low, mid, high):
    """The colormap of t, or rgb in a colour scene."""
    color = rgb
    if not colored:
        color = palette(position_on_path(t, e, low, mid, high))
    return color


@ti.func
def surface_color(grid_t: ti.template(), grid_c: ti.template(), q, dirn, light, inv_dx, colored, e, low, mid,
                  high):
    """The shaded colour of the surface point q hit along dirn: Lambert lighting of the field's outward normal
    (minus the gradient of the linear interpolant), the colormap of t BENEATH cells beneath (or c / m at q)."""
    m, g = trilinear_grad(grid_t, q, inv_dx)
    n = -dirn  # a flat field (no gradient): face the camera
    if g.norm() > 1e-12:
        n = -g.normalized()
    lit = AMBIENT + (1.0 - AMBIENT) * ti.max(n.dot(light), 0.0)
    rgb = ti.Vector([0.0, 0.0, 0.0])
    if colored:
        rgb = ti.math.clamp(trilinear_at(grid_c, q, inv_dx) / ti.max(m, 1e-12), 0.0, 1.0)
    beneath = trilinear_at(grid_t, q + BENEATH / inv_dx * dirn, inv_dx)
    return lit * shade_color(beneath, rgb, colored, e, low, mid, high)


@ti.func
def cell_corners(grid_t: ti.template(), i):
    """The 8 node values of cell i (nodes i to i + 1 on each axis; 0 <= i <= n - 2, so all inside the grid), corner o
    at index 4 o0 + 2 o1 + o2."""
    return ti.Vector([grid_t[i + ti.Vector([o0, o1, o2])] for o0 in ti.static(range(2)) for o1 in ti.static(range(2))
                      for o2 in ti.static(range(2))])


@ti.func
def lerp_along(p0, p1, u, du):
    """p0 (1 - w) + p1 w with w = u + du s, for polynomials p0, p1 in s (coefficient vectors, lowest first): one
    degree more."""
    base, rise = p0 + u * (p1 - p0), du * (p1 - p0)  # the weight's constant part, its part in s (shifted up)
    n = ti.static(p0.n)
    return ti.Vector([base[0]] + [base[j] + rise[j - 1] for j in ti.static(range(1, n))] + [rise[n - 1]])


@ti.func
def cell_cubic(g, o, dirn, s, i, inv_dx):
    """Coefficients (k0, k1, k2, k3) of the trilinear interpolant of cell i's corners g (cell_corners) along the ray
    o + (s + s') dirn, as a function of s': in cell units the ray is u + s' du, and interpolating linearly along one
    axis after the other (lerp_along) raises the degree by one each time, so the interpolant is a cubic in s'."""
    u, du = (o + s * dirn) * inv_dx - ti.cast(i, float), dirn * inv_dx
    # corner index 4 o0 + 2 o1 + o2: along axis 0 pairs (j, j + 4), then axis 1 (j, j + 2), then axis 2 (0, 1)
    l0 = [lerp_along(ti.Vector([g[j]]), ti.Vector([g[j + 4]]), u[0], du[0]) for j in ti.static(range(4))]
    l1 = [lerp_along(l0[j], l0[j + 2], u[1], du[1]) for j in ti.static(range(2))]
    return lerp_along(l1[0], l1[1], u[2], du[2])


@ti.func
def cubic_at(k, s):
    return k[0] + s * (k[1] + s * (k[2] + s * k[3]))


@ti.func
def turning_points(k, length):
    """The roots of the cubic k's derivative inside [0, length], in order (length where there are fewer than two):
    they cut [0, length] into three pieces (some empty) on each of which k is monotonic."""
    cuts = ti.Vector([length, length])
    a, b, c = 3.0 * k[3], 2.0 * k[2], k[1]  # k'(s) = a s^2 + b s + c
    if ti.abs(a) > 1e-12 * (ti.abs(b) + ti.abs(c)):  # a quadratic: two roots, or none (k' keeps its sign)
        disc = b * b - 4.0 * a * c
        if disc > 0.0:
            q = -0.5 * (b + ti.select(b >= 0.0, 1.0, -1.0) * ti.sqrt(disc))  # q != 0; the roots q / a, c / q
            cuts = ti.Vector([ti.min(q / a, c / q), ti.max(q / a, c / q)])
    elif ti.abs(b) > 0.0:  # linear
        cuts[0] = -c / b
    return ti.math.clamp(cuts, 0.0, length)


@ti.func
def cubic_max(k, length):
    """The largest value of the cubic k on [0, length]: at an end or at a turning point."""
    cuts = turning_points(k, length)
    return ti.max(ti.max(cubic_at(k, 0.0), cubic_at(k, length)), ti.max(cubic_at(k, cuts[0]), cubic_at(k, cuts[1])))


@ti.func
def first_crossing(k, iso, length):
    """The least s in [0, length] where the cubic k (cell_cubic) reaches iso, or -1 where it stays below.

    Of the pieces of turning_points, in order, the first that ends at or above iso holds the crossing (each earlier
    piece ended below iso, so this one starts below it, and k is monotonic on it); ROOT_STEPS halvings of that
    bracket, then the chord's zero in the last one: within 2^-ROOT_STEPS of a cell, far below a pixel at any
    render size."""
    cuts = turning_points(k, length)
    hit = -1.0
    if cubic_at(k, 0.0) >= iso:
        hit = 0.0
    else:
        lo, a, b = 0.0, 0.0, -1.0
        for piece in ti.static(range(3)):
            hi = length
            if ti.static(piece < 2):
                hi = cuts[piece]
            if b < 0.0 and hi > lo and cubic_at(k, hi) >= iso:
                a, b = lo, hi
            lo = ti.max(lo, hi)
        if b >= 0.0:
            fa, fb = cubic_at(k, a) - iso, cubic_at(k, b) - iso  # fa < 0 <= fb
            for _ in range(ROOT_STEPS):
                mid = 0.5 * (a + b)
                fm = cubic_at(k, mid) - iso
                if fm >= 0.0:
                    b, fb = mid, fm
                else:
                    a, fa = mid, fm
            hit = a + (b - a) * fa / (fa - fb)
    return hit


@ti.func
def cells_start(o, dirn, s, inv_dx, last):
    """The cells a ray o + s dirn crosses, in order (Amanatides and Woo's traversal), from its point at s: the cell
    i there (clamped to cells 0..last), the step (+1 or -1) along each axis, the ray's s at the cell's exit face on
    each axis, and the s between two faces of one axis."""
    dx = 1.0 / inv_dx
    i = ti.math.clamp(ti.cast(ti.floor((o + s * dirn) * inv_dx), ti.i32), 0, last)
    step = ti.Vector([1 if dirn[a] > 0.0 else -1 for a in ti.static(range(3))])
    t_face = ti.Vector([((i[a] + ti.select(step[a] > 0, 1, 0)) * dx - o[a]) / dirn[a] for a in ti.static(range(3))])
    t_cell = ti.Vector([dx / ti.abs(dirn[a]) for a in ti.static(range(3))])
    return i, step, t_face, t_cell


@ti.func
def cells_next(i, step, t_face, t_cell, last):
    """(i, t_face) of the next cell, through the face the ray reaches first, and whether it is a cell of the grid
    (0..last on each axis)."""
    a = 0
    if t_face[1] < t_face[a]:
        a = 1
    if t_face[2] < t_face[a]:
        a = 2
    for d in ti.static(range(3)):
        if d == a:
            i[d] += step[d]
            t_face[d] += t_cell[d]
    return i, t_face, i.min() >= 0 and i.max() <= last


@ti.func
def walk_cells(grid_t: ti.template(), o, dirn, t0, t1, inv_dx, iso, peak: ti.template()):
    """Along the ray o + s dirn, s in [t0, t1], cell by cell (cells_start, cells_next), the trilinear interpolant of
    grid_t exactly: with peak False, the least s where it reaches iso (first_crossing in the first cell whose largest
    corner reaches iso and whose cubic does), -1 where it stays below; with peak True, its largest value (cubic_max
    in every cell whose largest corner could raise it; iso unused)."""
    last = grid_t.shape[0] - 2  # the last cell: nodes n - 2 and n - 1
    result = 0.0 if ti.static(peak) else -1.0
    if t0 <= t1:
        i, step, t_face, t_cell = cells_start(o, dirn, t0, inv_dx, last)
        s = t0
        while s < t1:
            s_out = ti.max(s, ti.min(t_face.min(), t1))
            g = cell_corners(grid_t, i)
            if ti.static(peak):
                if g.max() > result:
                    result = ti.max(result, cubic_max(cell_cubic(g, o, dirn, s, i, inv_dx), s_out - s))
            elif g.max() >= iso:  # the interpolant in the cell is at most its largest corner
                hit = first_crossing(cell_cubic(g, o, dirn, s, i, inv_dx), iso, s_out - s)
                if hit >= 0.0:
                    result = s + hit
                    break
            i, t_face, inside = cells_next(i, step, t_face, t_cell, last)
            s = s_out
            if not inside:
                break
    return result


@ti.kernel
def march_surface(grid_t: ti.template(), grid_c: ti.template(), image: ti.template(), cam: ti.template(),
                  lo: ti.types.vector(3, float), hi: ti.types.vector(3, float), inv_dx: float, colored: ti.i32,
                  iso: float, e: float, low: float, mid: float, high: float):
    """The surface mode: each ray's first point where t reaches iso, shaded (`surface_color`); white elsewhere.

    Exact for the trilinear interpolant: the ray walks the cells it crosses in order (Amanatides and Woo's
    traversal), and in a cell whose largest corner reaches iso solves for the first crossing of the cubic the
    interpolant is along the ray (walk_cells, first_crossing). A march by fixed steps missed sheets thinner than its
    step along the ray, which showed as combs of stripes where a thin part is seen edge-on."""
    size = image.shape[0]
    light = (LIGHT_MIX[0] * cam[0] + LIGHT_MIX[1] * cam[2] + LIGHT_MIX[2] * cam[1]).normalized()
    for r, c in image:
        o, dirn = ray(r, c, size, cam)
        t0, t1 = box_span(o, dirn, lo, hi)
        hit = walk_cells(grid_t, o, dirn, t0, t1, inv_dx, iso, False)
        if hit >= 0.0:
            put(image, r, c, to_u8(surface_color(grid_t, grid_c, o + hit * dirn, dirn, light, inv_dx, colored, e, low,
                                                 mid, high)))


@ti.kernel
def march_volume(grid_t: ti.template(), grid_c: ti.template(), image: ti.template(), cam: ti.template(),
                 lo: ti.types.vector(3, float), hi: ti.types.vector(3, float), inv_dx: float, colored: ti.i32,
                 e: float, low: float, mid: float, high: float):
    """The volume mode: front-to-back emission-absorption compositing along each ray, on white."""
    size = image.shape[0]
    h = 0.5 / inv_dx
    for r, c in image:
        o, dirn = ray(r, c, size, cam)
        t0, t1 = box_span(o, dirn, lo, hi)
        acc = ti.Vector([0.0, 0.0, 0.0])
        T = 1.0  # transmittance so far
        s = t0
        while s <= t1 and T > 1e-3:
            p = o + s * dirn
            t = trilinear_at(grid_t, p, inv_dx)
            if t > e:
                rgb = ti.Vector([0.0, 0.0, 0.0])
                if colored:
                    rgb = ti.math.clamp(trilinear_at(grid_c, p, inv_dx) / t, 0.0, 1.0)
                alpha = 1.0 - ti.exp(-VOLUME_DENSITY * t * h * inv_dx)
                acc += T * alpha * shade_color(t, rgb, colored, e, low, mid, high)
                T *= 1.0 - alpha
            s += h
        if T < 1.0:
            put(image, r, c, to_u8(acc + T * ti.Vector([1.0, 1.0, 1.0])))


@ti.kernel
def peak_along_rays(grid_t: ti.template(), peak: ti.template(), cam: ti.template(), inv_dx: float):
    """peak[r, c] = the largest t along pixel (r, c)'s ray through the grid (a target's silhouette field): the largest
    of the cubics (cell_cubic) of the cells it crosses whose largest corner could raise it, so that a thin part is
    not stepped over (as march_surface). Beyond the last node the interpolant only falls, so the ray is followed to
    the box of the nodes."""
    size = peak.shape[0]
    far = (grid_t.shape[0] - 1) / inv_dx
    for r, c in peak:
        o, dirn = ray(r, c, size, cam)
        t0, t1 = box_span(o, dirn, ti.Vector([0.0, 0.0, 0.0]), ti.Vector([far, far, far]))
        peak[r, c] = walk_cells(grid_t, o, dirn, t0, t1, inv_dx, 0.0, True)


@ti.kernel
def splat_spheres(depth: ti.template(), image: ti.template(), cam: ti.template(), x: ti.types.ndarray(),
                  colors: ti.types.ndarray(), n: ti.i32, radius: float, colored: ti.i32,
                  body: ti.types.vector(3, float)):
    """The particles as shaded spheres of `radius` pixels, the nearest one at each pixel."""
    size = image.shape[0]
    for I in ti.grouped(depth):
        depth[I] = ti.i64(0x7FFFFFFFFFFFFFFF)
    for p in range(n):
        q = ti.Vector([x[p, 0], x[p, 1], x[p, 2]]) - ti.Vector(CENTRE, dt=float)
        col = (q.dot(cam[1]) / cam[3][0] + 1.0) * size / 2.0
        row = (1.0 - q.dot(cam[2]) / cam[3][0]) * size / 2.0
        key = ti.cast((2.0 - q.dot(cam[0])) * 1e6, ti.i64) * ti.i64(1 << 32) + ti.cast(p, ti.i64)
        for rr in range(ti.max(ti.cast(ti.floor(row - radius), ti.i32), 0),
                        ti.min(ti.cast(ti.floor(row + radius), ti.i32), size - 1) + 1):
            for cc in range(ti.max(ti.cast(ti.floor(col - radius), ti.i32), 0),
                            ti.min(ti.cast(ti.floor(col + radius), ti.i32), size - 1) + 1):
                du = (ti.cast(cc, float) + 0.5 - col) / radius
                dv = (row - ti.cast(rr, float) - 0.5) / radius
                if du * du + dv * dv <= 1.0:
                    ti.atomic_min(depth[rr, cc], key)
    light = (LIGHT_MIX[0] * cam[0] + LIGHT_MIX[1] * cam[2] + LIGHT_MIX[2] * cam[1]).normalized()
    for rr, cc in depth:
        key = depth[rr, cc]
        if key != ti.i64(0x7FFFFFFFFFFFFFFF):
            p = ti.cast(key % ti.i64(1 << 32), ti.i32)
            q = ti.Vector([x[p, 0], x[p, 1], x[p, 2]]) - ti.Vector(CENTRE, dt=float)
            col = (q.dot(cam[1]) / cam[3][0] + 1.0) * size / 2.0
            row = (1.0 - q.dot(cam[2]) / cam[3][0]) * size / 2.0
            du = ti.math.clamp((ti.cast(cc, float) + 0.5 - col) / radius, -1.0, 1.0)
            dv = ti.math.clamp((row - ti.cast(rr, float) - 0.5) / radius, -1.0, 1.0)
            nrm = du * cam[1] + dv * cam[2] + ti.sqrt(ti.max(1.0 - du * du - dv * dv, 0.0)) * cam[0]
            rgb = ti.Vector([body[0], body[1], body[2]], dt=float)
            if colored:
                rgb = ti.Vector([colors[p, 0], colors[p, 1], colors[p, 2]], dt=float)
            lit = AMBIENT + (1.0 - AMBIENT) * ti.max(nrm.dot(light), 0.0)
            put(image, rr, cc, to_u8(lit * rgb))


@ti.kernel
def upload_3d(grid: ti.template(), values: ti.types.ndarray()):
    for i, j, k in grid:
        grid[i, j, k] = values[i, j, k]


@ti.kernel
def upload_3d_vec(grid: ti.template(), values: ti.types.ndarray()):
    for i, j, k in grid:
        grid[i, j, k] = ti.Vector([values[i, j, k, 0], values[i, j, k, 1], values[i, j, k, 2]])


@ti.data_oriented
class Preview3D:
    """Renders the preview frames of one 3D run; fields are allocated once here, `render` is called per frame.

    n_grid: simulation grid nodes per axis; size: image side in pixels; mode: one of MODES_3D; colored: show
    c(x) / m(x) (a colour scene's particle colours) instead of the mass colormap; thresholds: the colormap's
    levels (colormap.Thresholds); spacing: the particles' rest spacing in domain units (sets the sphere radius
    of the particles mode); target_level, line_width: the target outline's level and width in pixels.
    """

    def __init__(self, n_grid, size=512, mode="surface", colored=False, thresholds=None, spacing=None,
                 target_level=0.5, line_width=1):
        if mode not in MODES_3D:
            raise ValueError(f"mode = {mode!r}: expected one of {', '.join(MODES_3D)}")
        self.n_grid, self.size, self.mode, self.colored = int(n_grid), int(size), mode, bool(colored)
        self.thresholds = thresholds or Thresholds()
        self.target_level, self.line_width = float(target_level), int(line_width)
        d, right, up, half = camera()
        self.half = half
        spacing = 0.5 / self.n_grid if spacing is None else spacing
        self.radius = max(1.0, 0.5 * spacing * self.size / (2.0 * half))  # half the spacing, in pixels
        n, s = self.n_grid, self.size
        self.cam = ti.Vector.field(3, float, shape=4)  # d, right, up, (half, 0, 0)
        self.cam.from_numpy(np.stack([d, right, up, (half, 0.0, 0.0)]).astype(real_dtype()))
        self.grid_t = ti.field(float, shape=(n, n, n))  # m_i / (density dx^3): normalised node mass
        self.grid_c = ti.Vector.field(3, float, shape=(n, n, n) if colored else (1, 1, 1))  # c_i / (density dx^3)
        self.image = ti.Vector.field(3, ti.u8, shape=(s, s))  # RGB bytes [row, column]
        self.ink = ti.field(float, shape=(s, s))  # an outline's coverage (contour.draw_outline)
        self.depth = ti.field(ti.i64, shape=(s, s)) if mode == "particles" else None  # (depth, particle) keys
        self._target = None  # (grid field, pixel field, the array uploaded)

    def render(self, field, x=None, colors=None, target=None):
        """One frame, uint8 (size, size, 3). field: the frame's field3d.MassField; x, colors: the particles
        (P, 3) (particles mode); target: a (res, res, res) grid of the target's normalised masses (its node
        masses over density / res^3), whose silhouette is outlined."""
        th = self.thresholds
        fill_white(self.image)
        if self.mode == "particles":
            x = np.ascontiguousarray(x, real_dtype())
            rgb = np.ascontiguousarray(colors if colors is not None and self.colored else np.zeros((len(x), 3)),
                                       real_dtype())
            if len(x):
                splat_spheres(self.depth, self.image, self.cam, x, rgb, len(x), self.radius, int(self.colored),
                              ti.Vector(BODY_COLOR))
        else:
            t = field.t
            upload_3d(self.grid_t, np.ascontiguousarray(t, real_dtype()))
            if self.colored:
                upload_3d_vec(self.grid_c, np.ascontiguousarray(field.c / field.rest, real_dtype()))
            lo, hi = _live_box(t, th.empty)
            args = (self.grid_t, self.grid_c, self.image, self.cam, ti.Vector(lo), ti.Vector(hi), float(self.n_grid),
                    int(self.colored))
            if self.mode == "surface":
                march_surface(*args, ISO_LEVEL, *th.as_tuple())
            else:
                march_volume(*args, *th.as_tuple())
        if target is not None:
            draw_outline(self._target_peak(target), self.ink, self.image, self.target_level, float(self.line_width),
                         ti.Vector(TARGET_OUTLINE_COLOR))
        return self.image.to_numpy()

    def _target_peak(self, target):
        """The silhouette field of a normalised target grid; recomputed only when the grid changes."""
        target = np.asarray(target, np.float64)
        if self._target is None or not np.array_equal(self._target[2], target):
            res = target.shape[0]
            grid = ti.field(float, shape=target.shape)
            upload_3d(grid, np.ascontiguousarray(target, real_dtype()))
            peak = ti.field(float, shape=(self.size, self.size))
            peak_along_rays(grid, peak, self.cam, float(res))
            self._target = (grid, peak, target.copy())
        return self._target[1]


def estimate_bytes_3d(n_grid, n_particles, size, mode, word, target_res=None):
    """Bytes a Preview3D and one frame's outputs allocate, known before they are built: the fields of
    `__init__` (and of a target grid of resolution target_res), the numpy grids of field3d (m, c and the
    stencils of splat: 4^3 weights and indices per particle) and the copy of each frame."""
    n3, s2 = n_grid ** 3, size * size
    fields = word * (4 * n3 + 3 * 4) + s2 * (3 + word + (8 if mode == "particles" else 0))  # grids, cam; image, ink, depth
    target = word * (target_res ** 3 + s2) if target_res else 0
    numpy_grids = 8 * 4 * n3 * 2 + 64 * n_particles * (8 + 8 + 1) * 2  # m, c and a copy; stencil arrays and masks
    return fields + target + numpy_grids + 3 * s2


def _live_box(t, empty):
    """(lo, hi) corners of the box of the nodes with t > empty, one cell wider on each side, in domain units;
    an empty box (lo > hi) when there are none."""
    n = t.shape[0]
    idx = np.argwhere(t > empty)
    if not len(idx):
        return (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)
    lo = np.maximum(idx.min(axis=0) - 1, 0) / n
    hi = np.minimum(idx.max(axis=0) + 1, n - 1) / n
    return tuple(map(float, lo)), tuple(map(float, hi))
