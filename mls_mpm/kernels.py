"""Cubic B-spline weights and the 4^dim stencil (eq 1-2: N(x) = prod_d N1(x_d / dx)), for dim = 2 and 3."""
import itertools

import taichi as ti
from taichi.lang import impl

from .config import STENCIL


# Stencil loops: axis 0 of the 4^dim nodes is the outer loop, one "slab" of 4^(dim - 1) nodes per step of it,
# unrolled (ti.static). In the 2D forward kernels the outer loop is unrolled too (16 nodes: Taichi 1.7.4's
# ti.ad.Tape, the test oracle, differentiates the 2D runtime loop only with matrices scalarized). In 3D, and in the
# reverse kernels (adjoint/) in 2D as well, it is a runtime loop: the full 64-node unroll of the P2G, G2P and
# reverse kernels with the 3D stress takes LLVM over 20 minutes to compile, a slab of 16 seconds; the 2D reverse
# kernels, which no Tape differentiates, compile 1.7-2.9x faster so (either mode), with the same run time
# and bit-identical results (BENCHMARKS.md, "Compile time"). A forward kernel writes its outer loop as
#     if ti.static(dim == 2):
#         for i0 in ti.static(range(STENCIL)): acc = slab(..., i0, acc)
#     else:
#         for i0 in range(STENCIL): acc = slab(..., i0, acc)
# a reverse kernel as the second branch alone, with the accumulators passed through the slab function, so that
# every sum adds the nodes in the same order. A slab's axis-0 weight w[i0, 0] is read once a slab (node_N): a forward
# kernel's by axis0, a reverse kernel's from registers, rolled at each step of the loop (axis0_column, roll), since
# indexing a matrix by the runtime i0 goes through memory (the 2D backward executed 12% fewer instructions so,
# BENCHMARKS.md).
# Inside a slab, the sums of u_i (o_i - 1)^T (G2P's eq 19, reverse P2G's eq 60) run row by row, a row being 4 nodes
# along the last axis (row_offsets; 2D: the slab is one row): a middle axis's offset, shared by a row, multiplies
# the row's sum once (outer_slab), not each node's (3D G2P 1.1x faster on one thread).


def slab_offsets(dim):
    """The offsets along axes 1.. of one slab (4^(dim - 1) nodes, axis 1 outermost, as ti.ndrange) as tuples of
    Python ints; loop over them with `for o2 in ti.static(slab_offsets(dim))` so that the loop unrolls at compile
    time, and pass o2 on as a ti.template() (its entries stay ints that ti.static can test: `along_slab`)."""
    return tuple(itertools.product(range(STENCIL), repeat=dim - 1))


def row_offsets(dim):
    """The offsets along the middle axes 1..dim - 2 of the rows of one slab, a row being the slab's 4 nodes along
    the last axis: 2D one row, (); 3D four, (0,) .. (3,). Node k of row o1 is slab offset o1 + (k,)."""
    return tuple(itertools.product(range(STENCIL), repeat=dim - 2))


@ti.func
def join(i0, o2: ti.template()):
    """The node offset (i0, o2) of slab i0."""
    return ti.Vector([i0] + [o2[d] for d in ti.static(range(len(o2)))])


@ti.func
def scaled_add(r, v, k: ti.template()):
    """r + k v for a compile-time integer k: nothing for 0, an add or a subtract for +-1."""
    if ti.static(k == 1):
        r += v
    elif ti.static(k == -1):
        r -= v
    elif ti.static(k != 0):
        r += float(k) * v
    return r


@ti.func
def along_slab(a, M, o2: ti.template()):
    """a + sum_d (o2[d] - 1) M[:, d + 1]: at node (i0, o2) of slab i0, a quantity affine in the node offset o, whose
    value at (i0, 1, ..) is a and whose slope along axis d + 1 is M[:, d + 1], e.g. m_p v_p + G (o - fx) dx of eq
    16 with M = G dx and a = m_p v_p + G ((i0, 1, ..) - fx) dx. The offsets are compile-time ints: a node costs a
    few adds where G (x_i - x_p) costs dim^2 multiply-adds. Centred on node 1 (offsets -1..2, fx - 1 in [0, 1)) so
    that no term is larger than in (o - fx) itself: the float32 round-off stays that of the direct product."""
    r = a
    for d in ti.static(range(len(o2))):
        r = scaled_add(r, M[:, d + 1], o2[d] - 1)
    return r


@ti.func
def outer_column(Q, u, c: ti.template(), o: ti.template()):
    """Q + u (o - 1) e_c^T: column c's term of one node (or row sum) u at stencil offset o along axis c."""
    for r in ti.static(range(u.n)):
        Q[r, c] = scaled_add(Q[r, c], u[r], o - 1)
    return Q


@ti.func
def outer_slab(Q, u, o2: ti.template()):
    """Q + u (0, o2 - 1)^T: the term of node (i0, o2), or of the sum u of row o2 (row_offsets), in
    sum_i u_i (o_i - 1)^T along axes 1..len(o2) (the caller adds i0 - 1 times the slab's sum of u for axis 0, and
    outer_row the last axis's terms of a row's nodes). With the sum of u_i, it gives sum_i u_i (x_i - x_p)^T =
    dx (sum_i u_i (o_i - 1)^T - (sum_i u_i) (fx - 1)^T) (eq 19, 60) in a few adds per node instead of dim^2
    multiply-adds, centred as along_slab."""
    for d in ti.static(range(len(o2))):
        Q = outer_column(Q, u, d + 1, o2[d])
    return Q


@ti.func
def outer_row(Q, u, k: ti.template()):
    """Q + u (0, .., 0, k - 1)^T: node k of a row's term of sum_i u_i (o_i - 1)^T along the last axis; a row's
    middle axes take the row's sum of u once (outer_slab), not each node's."""
    return outer_column(Q, u, Q.m - 1, k)


@ti.func
def stencil(x, inv_dx):
    """base = floor(x/dx) - 1 and the fractional offset fx = x/dx - base, in [1, 2) per axis."""
    base = ti.cast(ti.floor(x * inv_dx), ti.i32) - 1
    fx = x * inv_dx - ti.cast(base, float)
    return base, fx


@ti.func
def weights(fx):
    """Rows j = 0..3, one column per axis: N1(t) and dN1/dt with t = fx - j.

    N1(t) = |t|^3/2 - t^2 + 2/3 for |t| < 1 and (2 - |t|)^3/6 for 1 <= |t| < 2. Since fx is in [1, 2),
    row j always falls in the same piece, so the weights need no branch.
    """
    t0 = fx
    t1 = fx - 1.0
    t2 = fx - 2.0
    t3 = fx - 3.0
    w = ti.Matrix.rows([
        (2.0 - t0) ** 3 / 6.0,
        0.5 * t1 ** 3 - t1 ** 2 + 2.0 / 3.0,
        -0.5 * t2 ** 3 - t2 ** 2 + 2.0 / 3.0,
        (2.0 + t3) ** 3 / 6.0,
    ])
    dw = ti.Matrix.rows([
        -0.5 * (2.0 - t0) ** 2,
        1.5 * t1 ** 2 - 2.0 * t1,
        -1.5 * t2 ** 2 - 2.0 * t2,
        0.5 * (2.0 + t3) ** 2,
    ])
    return w, dw


def scalarized() -> bool:
    """Whether the running Taichi scalarizes matrices (the 3D Tape oracle's setting, runtime.needs_scalarized)."""
    return bool(impl.current_cfg().force_scalarize_matrix)


def spirv() -> bool:
    """Whether the running Taichi compiles to SPIR-V (Vulkan): see axis0."""
    return impl.current_cfg().arch == ti.vulkan


@ti.func
def axis0(w, i0):
    """w[i0, 0], the axis-0 weight of stencil row i0. Where Taichi scalarizes matrices (the 3D Tape oracle) and i0
    is the runtime loop's, by ti.select: its autodiff cannot take a matrix index that varies at run time. On
    Vulkan by ti.select too: Taichi 1.7.4's SPIR-V code generator fails on a kernel whose parallel loops each index
    a matrix at run time ('Value "tmpN" does not yet exist': the constants of one loop's index arithmetic are shared
    with the next loop, a function of its own in SPIR-V). Else by index: the selects make the 3D production kernels
    compile about 3x slower on a CPU."""
    v = w[0, 0]
    if ti.static(isinstance(i0, int) or not (scalarized() or spirv())):
        v = w[i0, 0]
    else:
        for j in ti.static(range(1, STENCIL)):
            v = ti.select(i0 == j, w[j, 0], v)
    return v


@ti.func
def axis0_column(w):
    """(w[0, 0], .., w[3, 0]): the axis-0 weights of the stencil's rows, for a loop over i0 that takes them by roll."""
    return ti.Vector([w[j, 0] for j in ti.static(range(STENCIL))])


@ti.func
def roll(c):
    """(c[1], .., c[n - 1], c[0]): after `c = roll(c)` at the end of each step of the stencil's runtime loop over i0,
    c[0] is axis0_column's entry i0 at every step, kept in registers (no runtime index: see axis0). The reverse
    kernels, which no Tape differentiates, take their axis-0 weights so."""
    return ti.Vector([c[(j + 1) % c.n] for j in ti.static(range(c.n))])


@ti.func
def carry(v):
    """v itself, for a value computed before the stencil's runtime loop (3D) and read inside it: reassign it at the
    top of each iteration, `w = carry(w)`. Taichi 1.7.4's autodiff keeps the adjoint of such a value for one
    iteration only (the Tape oracle would then see one slab of the stencil); a local reassigned in the loop goes on
    its adstack instead and gets every iteration's adjoint. x * 1.0 is exact, and LLVM folds it away."""
    return v * 1.0


@ti.func
def node_N(w0, w, o2: ti.template()):
    """N(x_i - x_p) = prod_d N1 for node base + (i0, o2) (eq 1), given the slab's axis-0 weight w0 = axis0(w, i0).

    A slab function reads w0 (and dw0) once, not once a node: indexing a matrix by the runtime i0 stores the matrix
    to memory and loads the entry back at each use, which LLVM does not hoist out of the stencil loop."""
    N = w0
    for d in ti.static(range(len(o2))):
        N *= w[o2[d], d + 1]
    return N


@ti.func
def slab_dN_add(acc, w, dw, o2: ti.template(), c):
    """acc + c (prod_d w[o2[d], d + 1], and for each axis e >= 1 that product with dw in place of w on axis e):
    node (i0, o2)'s term of slab i0's sum of dN c, without its axis-0 factor (slab_dN ends the slab).

    sum_i dN_i c_i over a slab (eq 2: dN = inv_dx (dw0 w1 w2, w0 dw1 w2, w0 w1 dw2) in 3D) has the axis-0 factor
    dw0 or w0 in common: a node costs dim multiply-adds here instead of the dim^2 products of dN at every node.
    """
    dim = ti.static(len(o2) + 1)
    for e in ti.static(range(dim)):
        g = c
        for d in ti.static(range(1, dim)):
            g *= dw[o2[d - 1], d] if ti.static(d == e) else w[o2[d - 1], d]
        acc[e] += g
    return acc


@ti.func
def slab_dN(acc, w0, dw0, inv_dx):
    """sum_i dN_i c_i over slab i0 from slab_dN_add's sums acc: axis 0 times dw0 = dw[i0, 0], the others times
    w0 = w[i0, 0]."""
    r = acc * w0
    r[0] = acc[0] * dw0
    return r * inv_dx


@ti.func
def inside(base, n) -> ti.i32:
    """Whether the whole 4^dim stencil from base lies on the grid of n nodes per axis."""
    ok = 1
    for d in ti.static(range(base.n)):
        ok = ok and base[d] >= 0 and base[d] <= n - STENCIL
    return ok


@ti.func
def on_grid(I, grid: ti.template()) -> ti.i32:
    """Whether node I lies on the field `grid` (a loss grid's nodes beyond the domain are dropped)."""
    ok = 1
    for d in ti.static(range(I.n)):
        ok = ok and 0 <= I[d] < grid.shape[d]
    return ok


@ti.func
def splat_slab(grid: ti.template(), base, w, value, i0):
    w0 = axis0(w, i0)
    for o2 in ti.static(slab_offsets(base.n)):
        I = base + join(i0, o2)
        if on_grid(I, grid):
            grid[I] += node_N(w0, w, o2) * value


@ti.func
def splat_particle(grid: ti.template(), X, inv_dx, value):
    """P2G of one particle's value (m_p, eq 15, or m_p c_p, eq 12) onto the 4^dim nodes around X:
    grid[i] += N(x_i - X) value, nodes off the grid dropped (a loss grid's nodes beyond the domain)."""
    base, fx = stencil(X, inv_dx)
    w, _ = weights(fx)
    if ti.static(X.n == 2):  # the stencil's outer loop: see slab_offsets
        for i0 in ti.static(range(STENCIL)):
            splat_slab(grid, base, w, value, i0)
    else:
        for i0 in range(STENCIL):
            w = carry(w)
            splat_slab(grid, base, w, carry(value), i0)
