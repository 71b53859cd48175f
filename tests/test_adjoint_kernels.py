"""Each hand-written reverse kernel alone against ti.ad.Tape on its forward twin (thesis eq 41-71).

Technique: the forward kernel runs on a grad-enabled State inside ti.ad.Tape, followed by a scalar
L = sum_y w_y . y, a random linear functional of the kernel's outputs y, so the Tape's input gradients are
the vector-Jacobian products of the kernel with w. The reverse kernel runs on a plain State holding the same
inputs, with w put in the AdjointState as the upstream adjoint dL/dy. Every input adjoint must agree with the
Tape to a symmetric relative error of at most 1e-8 (both are exact in exact arithmetic; float64 round-off
through one kernel stays near 1e-14). The grid-operation test runs in 2D (16^2 grid) and in 3D (12^3 grid,
the smallest grid with walls of 3 cells): one code path, two dimensions (SimConfig.dim). The kernels with a
stencil loop run here in 2D; their 3D twins run in tests/test_tape3d.py (Taichi initialised for the 3D Tape)
and against central differences in tests/test_kernels3d.py.

Reverse kernels accumulate (+=) into adjoints they share with other kernels, so those adjoints are
prefilled with random values b and the test compares (result - b) with the Tape.

Tape(validation=True) is not used here: Taichi only checks the global data access rule under
ti.init(debug=True), and this session runs without debug (re-initialising would invalidate every other test's
fields). test_gradients.py::test_forward_kernels_pass_tape_validation runs that check in a subprocess (slow).
"""
from types import SimpleNamespace

import numpy as np
import pytest
import taichi as ti

from adjoint.grid import grid_op_reverse
from adjoint.losses import evaluate_reverse, grid_loss_reverse, ot_loss_reverse, position_loss_reverse, splat_reverse
from adjoint.material import stress_reverse
from adjoint.state import AdjointState, zero_step
from adjoint.persistent import run_persistent_reverse
from adjoint.step import run_parallel_reverse, run_serial_reverse
from adjoint.transfer import g2p_reverse, p2g_reverse
from conftest import max_rel_err, rel_err
from mls_mpm import ColorLoss, MassLoss, OTLoss, SimConfig, losses, ot
from mls_mpm.grid import grid_op
from mls_mpm.material import stress
from mls_mpm.state import State, pack_mp_np, unpack_mp, unpack_mp_np, upload_loss
from mls_mpm.persistent import run_persistent
from mls_mpm.step import run_parallel, run_serial
from mls_mpm.transfer import g2p, p2g

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

TOL = 1e-8
N_PARTICLES = 48
OUTSIDE = 5  # a particle whose stencil leaves the grid: forward and reverse kernels both skip it

# steps = 3, stride = 2: step 2 is a control step (control k = 1, exercising f // stride), step 1 is not.
KERNEL_CFG = dict(n_grid=16, steps=3, dt=2e-3, E=400.0, nu=0.3, density=1.0, gamma=40.0, gravity=(0.3, -9.8),
                  bound=3, stride=2, particles_per_cell=4, dtype="f64", arch="cpu")
# the 3D twin: a 12^3 grid, gravity with a z component so that every axis of the walls and eq 17 is exercised
KERNEL_CFG_3D = {**KERNEL_CFG, "dim": 3, "n_grid": 12, "gravity": (0.3, -9.8, 0.7)}
DIMS = [2, 3]


def kernel_config(dim, **changes):
    return SimConfig(**{**(KERNEL_CFG if dim == 2 else KERNEL_CFG_3D), **changes})
CONTROL_STEP, PLAIN_STEP = 2, 1


# ------------------------------------------------------------------ the random functional and its seeding
@ti.data_oriented
class Upstream:
    """Weights w of L = sum w . y over particle outputs (x, v, C, F) and grid outputs (m, p, v)."""

    def __init__(self, n_particles, n_grid, dim=2):
        N, grid, d = n_particles, (n_grid,) * dim, dim
        self.dim = d
        self.x = ti.Vector.field(d, ti.f64, shape=N)
        self.v = ti.Vector.field(d, ti.f64, shape=N)
        self.C = ti.Matrix.field(d, d, ti.f64, shape=N)
        self.F = ti.Matrix.field(d, d, ti.f64, shape=N)
        self.m = ti.field(ti.f64, shape=grid)
        self.p = ti.Vector.field(d, ti.f64, shape=grid)
        self.gv = ti.Vector.field(d, ti.f64, shape=grid)
        self.np = {}

    def draw(self, rng, which):
        """Random normal weights for the outputs named in `which`, zero for the others."""
        for name in ("x", "v", "C", "F", "m", "p", "gv"):
            field = getattr(self, name)
            d = self.dim
            shape = field.shape + (() if name == "m" else (d,) if name in ("x", "v", "p", "gv") else (d, d))
            w = rng.standard_normal(shape) if name in which else np.zeros(shape)
            field.from_numpy(w)
            self.np[name] = w
        return self


@ti.kernel
def particle_functional(s: ti.template(), w: ti.template(), f: ti.i32):
    for p in range(s.n_particles):
        s.loss[None] += (w.x[p].dot(s.x[f, p]) + w.v[p].dot(s.v[f, p]) + (w.C[p] * s.C[f, p]).sum()
                         + (w.F[p] * s.F[f, p]).sum())


@ti.kernel
def grid_functional(s: ti.template(), w: ti.template(), f: ti.i32):
    for I in ti.grouped(ti.ndrange(*s.grid_shape)):
        p, m = unpack_mp(s.grid_mp[f, I])
        s.loss[None] += w.m[I] * m + w.p[I].dot(p) + w.gv[I].dot(s.grid_v[f, I])


PARTICLE_FIELDS = ("x", "v", "C", "F")


class Pair:
    """The same inputs in a grad-enabled State (for the Tape) and a plain State with its AdjointState."""

    def __init__(self, cfg, n_particles=N_PARTICLES, **state_kw):
        self.cfg = cfg
        self.t = State(cfg, n_particles, needs_grad=True, **state_kw)
        self.s = State(cfg, n_particles, every_velocity=True, **state_kw)  # v_i of every step, as the Tape's
        self.a = AdjointState(self.s, ti.f64)
        self.upstream = Upstream(n_particles, cfg.n_grid, cfg.dim)
        self.N, self.n, self.d = n_particles, cfg.n_grid, cfg.dim

    def put(self, name, value):
        getattr(self.t, name).from_numpy(value)
        if name != "grid_v" or self.s.every_velocity:  # one velocity slot (StepPair): the forward step writes it
            getattr(self.s, name).from_numpy(value)

    def put_grid(self, m, p):
        """Node masses m (steps,) + grid and momenta p (steps,) + grid + (dim,) into grid_mp (state.pack_mp's
        layout)."""
        self.put("grid_mp", pack_mp_np(p, m))

    def randomize(self, rng):
        """Random inputs at every step: x inside the grid (one particle outside), v, C ~ O(1), F near I."""
        T1, N, n, K, d = self.cfg.steps + 1, self.N, self.n, self.cfg.n_controls, self.d
        grid = (n,) * d
        lo, hi = 1.5 / n, 1.0 - 2.5 / n
        x = rng.uniform(lo, hi, (T1, N, d))
        x[:, OUTSIDE] = (0.3 / n,) + (0.5,) * (d - 1)  # base = floor(x / dx) - 1 = -1: the stencil leaves the grid
        self.put("x", x)
        self.put("v", rng.standard_normal((T1, N, d)))
        self.put("C", 3.0 * rng.standard_normal((T1, N, d, d)))
        self.put("F", np.eye(d) + 0.2 * rng.standard_normal((T1, N, d, d)))
        self.put("F_pc", 0.1 * rng.standard_normal((K, N, d, d)))
        self.put_grid(self.cfg.m_p * rng.uniform(0.1, 3.0, (T1 - 1,) + grid),
                      self.cfg.m_p * rng.standard_normal((T1 - 1,) + grid + (d,)))
        self.put("grid_v", rng.standard_normal((T1 - 1,) + grid + (d,)))
        self.put("loss", np.zeros(()))

    def prefill(self, rng, names, like):
        """Write random values of the scale of `like[name]` into adjoints `names`; return them."""
        out = {}
        for name in names:
            field = getattr(self.a, name)
            scale = np.linalg.norm(like[name]) / np.sqrt(like[name].size) + 1e-12
            out[name] = scale * rng.standard_normal(field.shape + field_tail(field))
            field.from_numpy(out[name])
        return out


def field_tail(field):
    if isinstance(field, ti.MatrixField):
        return (field.n,) if field.ndim == 1 else (field.n, field.m)
    return ()


def put_grid_adjoint(a, adj_m, adj_p):
    """dL/dm_i, dL/dp_i into AdjointState.adj_grid_mp, which holds (dL/dp_i, dL/dm_i) per node."""
    a.adj_grid_mp.from_numpy(pack_mp_np(adj_p, adj_m))


def grid_adjoint(a):
    """(dL/dm_i, dL/dp_i) from AdjointState.adj_grid_mp."""
    adj_p, adj_m = unpack_mp_np(a.adj_grid_mp.to_numpy())
    return adj_m, adj_p


def tape_grads(t, names, index):
    return {name: getattr(t, name).grad.to_numpy()[index] for name in names}


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def pair():
    return Pair(kernel_config(2))


@pytest.fixture(scope="module", params=[(d, b) for d in DIMS for b in ("slip", "sticky")],
                ids=["2d-slip", "2d-sticky", "3d-slip", "3d-sticky"])
def grid_pair(request):
    dim, boundary = request.param
    return Pair(kernel_config(dim, boundary=boundary), n_particles=8)


# ------------------------------------------------------------------ reverse G2P
@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("which", ["x", "v", "C", "F", "x v C F"])
def test_g2p_reverse_matches_tape(pair, f, which):
    """g2p_reverse (g2p_particle_reverse on every particle, g2p_slab_reverse on each slab of its stencil; eq 47-48,
    57 first term, 66-69) vs Tape on g2p
    (eq 18-21): rel err <= 1e-8.

    dL/dv_i^f, dL/dx_p^f and dL/d(F + F_pc)_p^f from dL/d(x, v, C, F)^{f+1}; each output alone, then all.
    g2p reads neither v^f nor C^f, so adj_v, adj_C of step f must stay as they were.
    """
    rng = np.random.default_rng(10 * f + len(which))
    pair.randomize(rng)
    w = pair.upstream.draw(rng, which.split())
    t, s, a = pair.t, pair.s, pair.a
    with ti.ad.Tape(loss=t.loss):
        g2p(t, f)
        particle_functional(t, w, f + 1)
    tape = tape_grads(t, ("x", "F", "grid_v", "v", "C"), f)
    tape_F_pc = t.F_pc.grad.to_numpy()

    g2p(s, f)  # the reverse kernel reads C^{f+1} (eq 57) and v^{f+1} (sum_i N v_i, eq 18)
    src, dst = (f + 1) % 2, f % 2
    d = pair.d
    b = pair.prefill(rng, ("adj_x", "adj_v", "adj_C", "adj_F", "adj_grid_v"),
                     {"adj_x": np.tile(tape["x"], (2, 1, 1)), "adj_v": np.ones((2, pair.N, d)),
                      "adj_C": np.ones((2, pair.N, d, d)), "adj_F": np.tile(tape["F"], (2, 1, 1, 1)),
                      "adj_grid_v": tape["grid_v"]})
    for name in PARTICLE_FIELDS:  # slot src holds the upstream dL/d(x, v, C, F)^{f+1} = w
        b["adj_" + name][src] = w.np[name]
        getattr(a, "adj_" + name).from_numpy(b["adj_" + name])
    g2p_reverse(s, a, f)

    assert rel_err(a.adj_grid_v.to_numpy() - b["adj_grid_v"], tape["grid_v"]) <= TOL
    assert rel_err(a.adj_x.to_numpy()[dst] - b["adj_x"][dst], tape["x"]) <= TOL
    assert rel_err(a.adj_F.to_numpy()[dst] - b["adj_F"][dst], tape["F"]) <= TOL
    # eq 55: the control enters only through F + F_pc, so the Tape's dL/dF_pc equals dL/dF at a control step
    k = f // pair.cfg.stride
    if f % pair.cfg.stride == 0:
        assert rel_err(tape_F_pc[k], tape["F"]) <= 1e-14
    else:
        assert np.all(tape_F_pc == 0.0)
    # untouched: g2p has no v^f, C^f input, and the upstream slot is read-only
    assert np.all(tape["v"] == 0.0) and np.all(tape["C"] == 0.0)
    assert np.array_equal(a.adj_v.to_numpy()[dst], b["adj_v"][dst])
    assert np.array_equal(a.adj_C.to_numpy()[dst], b["adj_C"][dst])
    assert np.array_equal(a.adj_x.to_numpy()[src], w.np["x"])
    # the skipped particle gets nothing from either
    assert np.all(tape["x"][OUTSIDE] == 0.0) and np.all(tape["F"][OUTSIDE] == 0.0)


# ------------------------------------------------------------------ reverse grid operations
def grid_inputs(cfg, rng):
    """Grid mass with every case of the eq 17 guard: ordinary nodes, empty (0), and nearly empty (5e-11, 3e-10 m_p);
    grid momentum with velocities O(1), and small ones whose sign gravity flips (kind 3)."""
    grid, m_p = (cfg.n_grid,) * cfg.dim, cfg.m_p
    tiny = 1e-10 * m_p
    m = m_p * rng.uniform(0.05, 3.0, grid)
    kind = rng.integers(0, 8, grid)
    m[kind == 0] = 0.0
    m[kind == 1] = 0.5 * tiny
    m[kind == 2] = 3.0 * tiny
    v = 2.0 * rng.standard_normal(grid + (cfg.dim,))  # p = m v keeps node velocities O(1) at every mass
    # nodes where gravity flips the sign of v: p/m against g, |p/m| < dt |g|, so the wall mask must be taken
    # on p/m + dt g (the velocity the forward pass masks), not on p/m
    flip = kind == 3
    v[flip] = -0.5 * cfg.dt * np.asarray(cfg.gravity)
    return m, m[..., None] * v, kind


@pytest.mark.parametrize("f", [0, 2])
def test_grid_op_reverse_matches_tape(grid_pair, f):
    """grid_op_reverse (grid_op_node_reverse on every node; eq 49-53, gravity, walls) vs Tape on grid_op (eq 17):
    per-node rel err <= 1e-8.

    Covers wall-zone nodes (bound = 3 cells per side; slip masks one component, sticky all), empty nodes
    (divisor m_eps alone, checked in closed form too) and nodes of mass 5e-11 and 3e-10 m_p (adjoints ~ 1/m,
    so the error is measured node by node rather than by a norm over the grid).
    """
    pair = grid_pair
    cfg = pair.cfg
    rng = np.random.default_rng(f + (cfg.boundary == "sticky") + 10 * (cfg.dim == 3))
    pair.randomize(rng)
    m, p, kind = grid_inputs(cfg, rng)
    T = cfg.steps
    pair.put_grid(np.broadcast_to(m, (T,) + m.shape), np.broadcast_to(p, (T,) + p.shape))
    w = pair.upstream.draw(rng, ["gv"])
    t, s, a = pair.t, pair.s, pair.a
    with ti.ad.Tape(loss=t.loss):
        grid_op(t, f)
        grid_functional(t, w, f)
    tape = dict(zip(("grid_p", "grid_m"), unpack_mp_np(tape_grads(t, ("grid_mp",), f)["grid_mp"])))

    a.adj_grid_v.from_numpy(w.np["gv"])
    # grid_op_reverse owns dL/dm_i, dL/dp_i: it overwrites them
    put_grid_adjoint(a, rng.standard_normal(m.shape), rng.standard_normal(p.shape))
    grid_op_reverse(s, a, f)
    adj_m, adj_p = grid_adjoint(a)

    assert max_rel_err(adj_p, tape["grid_p"]) <= TOL
    assert max_rel_err(adj_m, tape["grid_m"], axis=None) <= TOL
    # empty nodes (m = 0) divide by m_eps = 1e-20 m_p alone: dL/dp = M g / m_eps and dL/dm = dt g . M g / m_eps
    # (gravity's impulse m dt g), M the wall mask; where the Tape passes dL/dp, M is 1
    m_eps = 1e-20 * cfg.m_p
    empty = m == 0.0
    g_masked = w.np["gv"] * (tape["grid_p"] != 0.0)
    assert rel_err(adj_p[empty], g_masked[empty] / m_eps) <= TOL
    assert rel_err(adj_m[empty], cfg.dt * g_masked[empty] @ np.asarray(cfg.gravity) / m_eps) <= TOL
    assert np.all(np.isfinite(adj_p)) and np.any(adj_p[empty] != 0.0)  # nothing is cut, nothing overflows
    b, n = cfg.bound, cfg.n_grid
    index = np.indices(m.shape)  # a node is in the wall zone when any of its indices is
    wall = np.any((index < b) | (index >= n - b), axis=0)
    light = (kind == 2) & ~wall
    assert np.any(light) and np.all(np.abs(adj_m[light]) > 0.0)  # nearly empty nodes pass gradient back
    # the walls really cut gradients in this test: some wall-zone component is zero in both
    cut = (tape["grid_p"] == 0.0) & ~empty[..., None]
    assert np.any(cut[wall]) and not np.any(cut[~wall])
    if cfg.boundary == "sticky":
        assert np.all(adj_p[wall] == 0.0)
    else:
        assert np.any(adj_p[wall] != 0.0)


# ------------------------------------------------------------------ reverse P2G
@pytest.mark.parametrize("f", [CONTROL_STEP, PLAIN_STEP])
@pytest.mark.parametrize("which", ["m", "p", "m p"])
def test_p2g_reverse_matches_tape(pair, f, which):
    """p2g_reverse (p2g_particle_reverse on every particle, p2g_slab_reverse on each slab of its stencil; eq 54-65,
    71) vs Tape on p2g (eq 14-16, drag
    gamma dt = 0.08): rel err <= 1e-8.

    dL/d(x, v, C, F)_p^f from dL/dm_i, dL/dp_i; at a control step (f = 2, k = 1) also dL/dF_pc^k, which
    p2g_reverse forms as dL/dF_pc^k += dL/dF_p^f (eq 55) after adding its own part to dL/dF_p^f.
    """
    rng = np.random.default_rng(100 + 10 * f + len(which))
    pair.randomize(rng)
    w = pair.upstream.draw(rng, which.split())
    t, s, a = pair.t, pair.s, pair.a
    for st in (t, s):
        st.grid_mp.fill(0.0)
    with ti.ad.Tape(loss=t.loss):
        p2g(t, f)
        grid_functional(t, w, f)
    tape = tape_grads(t, PARTICLE_FIELDS, f)
    tape_F_pc = t.F_pc.grad.to_numpy()

    put_grid_adjoint(a, w.np["m"], w.np["p"])
    like = {"adj_" + k: np.stack([tape[k]] * 2) for k in PARTICLE_FIELDS}
    like["adj_F_pc"] = tape_F_pc + tape["F"]
    b = pair.prefill(rng, list(like), like)
    p2g_reverse(s, a, f)

    dst = f % 2
    for name in PARTICLE_FIELDS:
        got = getattr(a, "adj_" + name).to_numpy()
        assert rel_err(got[dst] - b["adj_" + name][dst], tape[name]) <= TOL, name
        assert np.array_equal(got[1 - dst], b["adj_" + name][1 - dst]), name  # the other slot is untouched
        assert np.all(tape[name][OUTSIDE] == 0.0)
    got_F_pc = a.adj_F_pc.to_numpy() - b["adj_F_pc"]
    k = f // pair.cfg.stride
    if f % pair.cfg.stride == 0:
        assert rel_err(tape_F_pc[k], tape["F"]) <= 1e-14  # eq 55 in the oracle itself
        # dL/dF_pc^k += everything dL/dF_p^f holds, the prefill standing in for the G2P part (eq 57);
        # a skipped particle (its stencil left the grid) has no G2P part either, so it gets nothing
        expected = b["adj_F"][dst] + tape_F_pc[k]
        expected[OUTSIDE] = 0.0
        assert rel_err(got_F_pc[k], expected) <= TOL
        others = [j for j in range(pair.cfg.n_controls) if j != k]
        assert np.all(got_F_pc[others] == 0.0)
    else:
        assert np.all(tape_F_pc == 0.0) and np.all(got_F_pc == 0.0)


# ------------------------------------------------------------------ one whole reverse step, both schedules
LANES = 2


class StepPair(Pair):
    """A Pair whose plain State runs the production step: with LANES private grids per thread, or serially, and
    one grid velocity slot (the reverse pass recomputes v_i from m_i, p_i)."""

    def __init__(self, cfg, lanes):
        super().__init__(cfg)
        self.s = State(cfg, self.N, lanes=lanes)
        self.a = AdjointState(self.s, ti.f64)


@pytest.fixture(scope="module")
def step_pairs():
    cfg = kernel_config(2)
    return {"parallel": StepPair(cfg, LANES), "serial": StepPair(cfg, 0)}


def run_step_pair(pair, f, w, upstream_nan=(), n=1, persistent=False):
    """Tape over steps f..f+n-1 (p2g, grid_op, g2p each) and the production reverse pass on the same inputs and
    upstream w. With n = 2 the pass crosses a step boundary: the reverse grid loop of step f + 1 recomputes the
    grid velocity of step f that the reverse G2P of step f reads (one velocity slot). persistent (a state with
    lanes): the passes in one launch each, run_persistent and run_persistent_reverse, done again (up to 3 times, then the test is
    skipped) if a barrier gave up because other work held the CPUs (persistent_pass_reverse, which Simulator.backward
    calls, then says so, and the pass runs again with run_parallel_reverse: tests/test_persistent.py drives it).

    Returns the Tape's dL/d(x, v, C, F)^f and dL/dF_pc. The upstream of the particles in upstream_nan is NaN.
    """
    t, s, a = pair.t, pair.s, pair.a
    for st in (t, s):
        st.grid_mp.fill(0.0)
    with ti.ad.Tape(loss=t.loss):
        for g in range(f, f + n):
            p2g(t, g)
            grid_op(t, g)
            g2p(t, g)
        particle_functional(t, w, f + n)
    tape = tape_grads(t, PARTICLE_FIELDS, f)
    tape["F_pc"] = t.F_pc.grad.to_numpy()
    for _ in range(3 if persistent else 1):
        # the reverse pass reads the forward's stored states (C^{f+1} of eq 57, grid v^f), so the forward runs first
        if persistent:
            s.sync.fill(0)
            run_persistent(s, f, f + n)
        elif s.lanes:
            run_parallel(s, f, f + n)
        else:
            run_serial(s, f, f + n)
        forward_gave_up = persistent and s.sync[1] != 0
        zero_step(s, a, f)
        a.adj_F_pc.fill(0.0)
        a.fault[None] = -1
        src = (f + n) % 2
        for name in PARTICLE_FIELDS:
            up = np.zeros((2,) + w.np[name].shape)
            up[src] = w.np[name]
            up[src, list(upstream_nan)] = np.nan
            getattr(a, "adj_" + name).from_numpy(up)
        if persistent:
            s.sync.fill(0)
            run_persistent_reverse(s, a, f, f + n)
            if forward_gave_up or s.sync[1] != 0:
                s.lane_mp.fill(0.0)
                a.lane_adj_v.fill(0.0)
                continue
        elif s.lanes:
            run_parallel_reverse(s, a, f, f + n)
        else:
            run_serial_reverse(s, a, f, f + n)
        return tape
    pytest.skip("every one-launch pass gave up: other work held the CPUs")


@pytest.mark.parametrize("schedule", ["parallel", "persistent", "serial"])
@pytest.mark.parametrize("f, n", [(CONTROL_STEP, 1), (PLAIN_STEP, 1), (PLAIN_STEP, 2)])
def test_step_reverse_matches_tape(step_pairs, schedule, f, n):
    """A reverse pass of the production driver over steps f..f+n-1 vs Tape on p2g, grid_op, g2p of those steps:
    rel err <= 1e-8.

    parallel: run_parallel_reverse (grid_op for v_i of step f + n - 1, then per step substep_reverse, step_loops_reverse:
    g2p_particle_reverse into LANES private grids, summed by gather_lanes_reverse in grid_node_reverse, then
    p2g_particle_reverse and check_particle_reverse); persistent: the same loops, each lane's share, in one launch
    with barriers (run_persistent, run_persistent_reverse, on the parallel pair's state); serial: run_serial_reverse
    over [f, f + n).
    dL/d(x, v, C, F)^f and dL/dF_pc (eq 47-71); afterwards the consumed adjoints of step f + 1, dL/dv_i and the
    private grids are zero, and no fault is recorded. n = 2 also crosses the control step 2 (stride 2).
    """
    pair = step_pairs["parallel" if schedule == "persistent" else schedule]
    rng = np.random.default_rng(300 + f + 10 * (n - 1))
    pair.randomize(rng)
    w = pair.upstream.draw(rng, list(PARTICLE_FIELDS))
    tape = run_step_pair(pair, f, w, n=n, persistent=schedule == "persistent")
    a, dst = pair.a, f % 2
    for name in PARTICLE_FIELDS:
        got = getattr(a, "adj_" + name).to_numpy()
        assert rel_err(got[dst], tape[name]) <= TOL, name
        assert np.all(got[1 - dst] == 0.0), name  # consumed and zeroed
    assert rel_err(a.adj_F_pc.to_numpy(), tape["F_pc"]) <= TOL
    acts = any(g % pair.cfg.stride == 0 for g in range(f, f + n))
    assert acts == np.any(tape["F_pc"] != 0.0)
    assert np.all(a.adj_grid_v.to_numpy() == 0.0)
    if pair.s.lanes:
        assert np.all(a.lane_adj_v.to_numpy() == 0.0)
    assert a.fault[None] == -1


@pytest.mark.parametrize("schedule", ["parallel", "serial"])
def test_reverse_fault_names_the_lowest_particle(step_pairs, schedule):
    """record_fault_reverse keeps, in the latest reverse step, the lowest particle whose adjoint is non-finite,
    whatever the parallel order: NaN upstream on particles 30 and 9 spreads through the grid to their
    neighbours; the fault code must name the lowest index among all particles left non-finite."""
    pair = step_pairs[schedule]
    f = PLAIN_STEP
    rng = np.random.default_rng(400)
    pair.randomize(rng)
    w = pair.upstream.draw(rng, list(PARTICLE_FIELDS))
    run_step_pair(pair, f, w, upstream_nan=(30, 9))
    a, dst, N = pair.a, f % 2, pair.N
    bad = np.zeros(N, bool)
    for name in PARTICLE_FIELDS:
        adj = getattr(a, "adj_" + name).to_numpy()[dst].reshape(N, -1)
        bad |= ~np.all(np.isfinite(adj), axis=1)
    assert bad[9] and bad[30] and bad.sum() > 2
    lowest = int(np.flatnonzero(bad)[0])
    assert a.fault[None] == f * N + (N - 1 - lowest)


# ------------------------------------------------------------------ dP/dF contraction
@ti.kernel
def stress_functional(Fs: ti.template(), W: ti.template(), loss: ti.template(), mu: ti.f64, lam: ti.f64):
    for q in Fs:
        loss[None] += (W[q] * stress(Fs[q], mu, lam)).sum()


@ti.kernel
def stress_adjoint(Fs: ti.template(), W: ti.template(), out: ti.template(), mu: ti.f64, lam: ti.f64):
    for q in Fs:
        out[q] = stress_reverse(Fs[q], W[q], mu, lam)


def stress_cases():
    rng = np.random.default_rng(7)

    def rot(a):
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    cases = {
        "identity": np.eye(2),
        "a*I expand": 1.3 * np.eye(2),
        "a*I shrink": 0.6 * np.eye(2),
        "-a*I (trace < 0, R = -I)": -0.8 * np.eye(2),
        "rotation": rot(2.5),
        "rotated stretch": rot(-0.7) @ np.diag([1.4, 0.8]) @ rot(0.3),
        "shear": np.array([[1.0, 0.6], [0.0, 1.0]]),
        "nearly singular (J = 1e-9)": np.array([[1.0, 2.0], [0.5, 1.0 + 1e-9]]),
        "rank one": np.array([[1.0, 2.0], [0.5, 1.0]]),
        "J < 0 (reflection)": np.diag([1.0, -0.5]),
        "J < 0 rotated": rot(0.4) @ np.diag([0.9, -1.2]),
    }
    for q in range(10):
        cases[f"random {q}"] = np.eye(2) + 0.5 * rng.standard_normal((2, 2))
    return cases


def test_stress_reverse_matches_tape():
    """stress_reverse(F, G) = dP/dF : G (eq 57, second term; rotated_stress_reverse with R = polar_rotation(F)) vs
    Tape through stress (eq 9): rel err <= 1e-8.

    Per case: identity, a I, a rotation, shear, nearly singular and rank-one F, J < 0; G random.
    At F = I also against the closed form 2 mu sym(G) + lam tr(G) I, rel err <= 1e-14.
    """
    cases = stress_cases()
    names = list(cases)
    M = len(names)
    mu, lam = 123.4, 56.7
    rng = np.random.default_rng(8)
    Fs = ti.Matrix.field(2, 2, ti.f64, shape=M, needs_grad=True)
    W = ti.Matrix.field(2, 2, ti.f64, shape=M)
    out = ti.Matrix.field(2, 2, ti.f64, shape=M)
    loss = ti.field(ti.f64, shape=(), needs_grad=True)
    Fs.from_numpy(np.stack([cases[k] for k in names]))
    G = rng.standard_normal((M, 2, 2))
    W.from_numpy(G)
    with ti.ad.Tape(loss=loss):
        stress_functional(Fs, W, loss, mu, lam)
    stress_adjoint(Fs, W, out, mu, lam)
    tape, got = Fs.grad.to_numpy(), out.to_numpy()
    for q, name in enumerate(names):
        assert rel_err(got[q], tape[q]) <= TOL, name
    # at F = I the result is linear elasticity's 2 mu sym(G) + lam tr(G) I; the rotation term cancels
    # the skew part of 2 mu G, so a missing or wrong-signed rotation term shows here
    q = names.index("identity")
    linear = mu * (G[q] + G[q].T) + lam * np.trace(G[q]) * np.eye(2)
    assert rel_err(got[q], linear) <= 1e-14
    assert rel_err(got[q], 2 * mu * G[q] + lam * np.trace(G[q]) * np.eye(2)) > 1e-3


def test_stress_reverse_singular_rotation_is_guarded():
    """Symmetric zero-trace F (atan2(0, 0): polar angle undefined): finite, rotation term dropped as documented.

    Expected: 2 mu G + lam (cof F : G) cof F + lam (J - 1) cof G, exact to 1e-14.
    """
    Fm = np.array([[1.0, 0.3], [0.3, -1.0]])
    G = np.array([[0.7, -1.1], [0.4, 2.0]])
    mu, lam = 10.0, 5.0
    Fs = ti.Matrix.field(2, 2, ti.f64, shape=1)
    W = ti.Matrix.field(2, 2, ti.f64, shape=1)
    out = ti.Matrix.field(2, 2, ti.f64, shape=1)
    Fs.from_numpy(Fm[None])
    W.from_numpy(G[None])
    stress_adjoint(Fs, W, out, mu, lam)

    def cof(A):
        return np.array([[A[1, 1], -A[1, 0]], [-A[0, 1], A[0, 0]]])

    J = np.linalg.det(Fm)
    expected = 2 * mu * G + lam * np.sum(cof(Fm) * G) * cof(Fm) + lam * (J - 1) * cof(G)
    assert rel_err(out.to_numpy()[0], expected) <= 1e-14


# ------------------------------------------------------------------ loss seeds
# the fine and coarse loss grids of the loss-seed tests: 16 and 8 per axis in 2D, 8 and 4 in 3D
LOSS_RES = {2: (16, 8), 3: (8, 4)}


def loss_specs(rng, dim=2):
    """Loss grids of every kind: mass fine and coarse with weights and a penalty grid alpha (eq 11, 72), log mass
    with alpha, color (eq 13; ColorLoss takes no alpha)."""
    hi, lo = LOSS_RES[dim]
    t16 = rng.uniform(0.0, 2.0, (hi,) * dim) * 1e-3
    t8 = rng.uniform(0.0, 2.0, (lo,) * dim) * 4e-3
    a16 = rng.uniform(1.0, 4.0, (hi,) * dim)
    c16 = rng.uniform(0.0, 1.0, (hi,) * dim + (3,)) * 1e-3
    colors = rng.uniform(0.0, 1.0, (N_PARTICLES, 3))
    grids = (MassLoss([t16, t8], weights=[2.0, 0.5], alpha=[a16, None]).grids
             + MassLoss([t16], alpha=[a16], log=True).grids
             + ColorLoss([c16], colors=colors, weights=[1.5]).grids)
    return grids, colors


LOSS_GRIDS = ["mass fine alpha w=2", "mass coarse w=0.5", "log mass fine alpha", "color fine w=1.5"]
EDGE_X = {2: [(0.04, 0.5), (0.97, 0.2), (0.5, 0.03), (0.96, 0.98)],
          3: [(0.04, 0.5, 0.5), (0.97, 0.2, 0.6), (0.5, 0.03, 0.4), (0.96, 0.98, 0.97)]}


@pytest.fixture(scope="module")
def loss_pair():
    return make_loss_pair(2)


def make_loss_pair(dim):
    """A Pair with loss grids of every kind (loss_specs), colours, a position target and random inputs."""
    rng = np.random.default_rng(21)
    grids, colors = loss_specs(rng, dim)
    pair = Pair(kernel_config(dim), loss_grids=grids, position_loss=True, colors=True)
    target_x = rng.uniform(0.2, 0.8, (N_PARTICLES, dim))
    for st in (pair.t, pair.s):
        for g, spec in zip(st.loss_grids, grids):
            g.target.from_numpy(spec.target)
            if spec.alpha is not None:
                g.alpha.from_numpy(spec.alpha)
        st.color.from_numpy(colors)
        st.target_x.from_numpy(target_x)
    pair.randomize(rng)
    # a few particles near the domain edges, so loss-grid nodes beyond the domain are dropped (splat)
    x = pair.s.x.to_numpy()
    x[:, :4] = EDGE_X[dim]
    pair.put("x", x)
    return pair


def run_loss_tape(pair, f, grids, position):
    t = pair.t
    for g in t.loss_grids:
        g.m.fill(0.0)
    with ti.ad.Tape(loss=t.loss):
        for gi in grids:
            losses.splat(t, t.loss_grids[gi], f)
            losses.grid_loss(t, t.loss_grids[gi])
        if position:
            losses.position_loss(t, f)
    return t.x.grad.to_numpy()[f], t.loss[None]


@pytest.mark.parametrize("gi", range(len(LOSS_GRIDS)), ids=LOSS_GRIDS)
def test_grid_loss_seed_matches_tape(loss_pair, gi):
    """grid_loss_reverse (eq 41, 72; log: r / (m + 1)) and splat_reverse (eq 42-43) vs Tape on splat + grid_loss.

    dL/dm_i per node and dL/dx_p^{N_t}, rel err <= 1e-8; the kernels' own loss agrees with a numpy one.
    """
    pair, f = loss_pair, 3
    tape_x, tape_loss = run_loss_tape(pair, f, [gi], position=False)
    s, a = pair.s, pair.a
    g, tg = s.loss_grids[gi], pair.t.loss_grids[gi]
    g.m.fill(0.0)
    losses.splat(s, g, f)
    rng = np.random.default_rng(gi)
    b = pair.prefill(rng, ["adj_x"], {"adj_x": np.stack([tape_x] * 2)})
    grid_loss_reverse(s, g)
    splat_reverse(s, g, a, f)

    assert max_rel_err(g.adj_m.to_numpy(), tg.m.grad.to_numpy()) <= TOL
    assert rel_err(a.adj_x.to_numpy()[f % 2] - b["adj_x"][f % 2], tape_x) <= TOL
    assert np.array_equal(a.adj_x.to_numpy()[1 - f % 2], b["adj_x"][1 - f % 2])
    # the loss value itself (eq 11, 13, 72 and the log mass loss), from the splatted grid
    m, target = g.m.to_numpy(), g.target.to_numpy()
    r = np.log(m + 1) - np.log(target + 1) if g.kind == "log_mass" else m - target
    alpha = g.alpha.to_numpy()[..., None] if g.has_alpha else 1.0
    assert rel_err(tape_loss, 0.5 * g.weight * np.sum(alpha * r ** 2)) <= 1e-12


def test_position_loss_seed_matches_tape(loss_pair):
    """position_loss_reverse: dL/dx_p = x_p - x_pu (eq 10) vs Tape on position_loss, rel err <= 1e-8."""
    pair, f = loss_pair, 3
    tape_x, _ = run_loss_tape(pair, f, [], position=True)
    b = pair.prefill(np.random.default_rng(5), ["adj_x"], {"adj_x": np.stack([tape_x] * 2)})
    position_loss_reverse(pair.s, pair.a, f)
    assert rel_err(pair.a.adj_x.to_numpy()[f % 2] - b["adj_x"][f % 2], tape_x) <= TOL
    expected = pair.s.x.to_numpy()[f] - pair.s.target_x.to_numpy()
    assert rel_err(tape_x, expected) <= 1e-14


def test_seed_sums_every_loss_and_zeroes_the_rest(loss_pair):
    """evaluate_reverse() (the loss seed, twin of losses.evaluate) zeroes both particle slots and dL/dv_i, then
    sums every grid's and the position term's dL/dx (eq 41-43, 10); dL/dv, dL/dF, dL/dC of step N_t are zero (eq 44-46). Rel err <= 1e-8 against one Tape of
    the full loss; the other slot, where reverse step N_t - 1 accumulates, must be exactly zero."""
    pair, f = loss_pair, 3
    tape_x, _ = run_loss_tape(pair, f, range(len(LOSS_GRIDS)), position=True)
    s, a = pair.s, pair.a
    for g in s.loss_grids:
        g.m.fill(0.0)
        losses.splat(s, g, f)
    pair.prefill(np.random.default_rng(6), ["adj_x", "adj_v", "adj_C", "adj_F", "adj_grid_v"],
                     {"adj_x": np.ones((2, pair.N, pair.d)), "adj_v": np.ones((2, pair.N, pair.d)),
                      "adj_C": np.ones((2, pair.N, pair.d, pair.d)), "adj_F": np.ones((2, pair.N, pair.d, pair.d)),
                      "adj_grid_v": np.ones((pair.n,) * pair.d + (pair.d,))})
    evaluate_reverse(s, a, f)
    slot = f % 2
    assert rel_err(a.adj_x.to_numpy()[slot], tape_x) <= TOL
    assert np.all(a.adj_x.to_numpy()[1 - slot] == 0.0)
    for name in ("adj_v", "adj_C", "adj_F"):
        assert np.all(getattr(a, name).to_numpy() == 0.0), name
    assert np.all(a.adj_grid_v.to_numpy() == 0.0)


# ------------------------------------------------------------------ the optimal-transport loss seed
def ot_specs(rng, dim=2):
    """OTLoss grids: a balanced transport term on the fine grid (w = 2) beside eq 11 on the coarse one (transport
    weight 0, mass weight 3), and an unbalanced transport term on the coarse one (reach 0.3, w = 0.5)."""
    hi, lo = LOSS_RES[dim]
    t16 = rng.uniform(0.0, 2.0, (hi,) * dim) * 1e-3
    t8 = rng.uniform(0.0, 2.0, (lo,) * dim) * 4e-3
    return (OTLoss([t16, t8], weights=[2.0, 0.0], mass_weights=[0.0, 3.0], blur=1.5).grids
            + OTLoss([t8], weights=[0.5], blur=1.0, reach=0.3).grids)


@pytest.fixture(scope="module")
def ot_pair():
    dim = 2
    rng = np.random.default_rng(31)
    specs = ot_specs(rng, dim)
    hi, lo = LOSS_RES[dim]
    assert [(g.kind, g.res) for g in specs] == [("ot", hi), ("mass", lo), ("ot", lo)]
    pair = Pair(kernel_config(dim), loss_grids=specs)
    for st in (pair.t, pair.s):
        upload_loss(st, SimpleNamespace(grids=specs))
    pair.randomize(rng)
    pair.specs = specs
    return pair


@pytest.mark.parametrize("gi", [0, 2], ids=["ot fine w=2", "ot coarse reach=0.3 w=0.5"])
def test_ot_loss_seed_matches_tape(ot_pair, gi):
    """ot_loss_reverse (dL/dm_i = the seed w dS/dm_i that ot_loss wrote) and splat_reverse vs Tape on splat +
    seed_loss (sum_i seed_i m_i, the Tape's linear stand-in, with the seed ot_loss writes in the grad State):
    dL/dm_i per node and dL/dx_p^{N_t}, rel err <= 1e-8.

    The seed itself must be w times ot.sinkhorn_divergence(m, m_u, blur / res, reach).grad computed here from the
    node masses read back (rel err <= 1e-12), and the loss w S: this checks the plumbing, not the formula
    (tests/test_ot.py checks the divergence and its gradient).
    """
    pair, f = ot_pair, 3
    s, t, a = pair.s, pair.t, pair.a
    g, tg, spec = s.loss_grids[gi], t.loss_grids[gi], pair.specs[gi]
    s.loss[None] = 0.0
    g.m.fill(0.0)
    losses.splat(s, g, f)
    value = losses.ot_loss(s, g)
    seed = g.seed.to_numpy()

    m = g.m.to_numpy()[..., 0]
    r = ot.sinkhorn_divergence(m, spec.target[..., 0], spec.blur / spec.res, spec.reach, tol=spec.tol)
    assert rel_err(seed[..., 0], spec.weight * r.grad) <= 1e-12
    assert rel_err(value, spec.weight * r.value) <= 1e-12 and s.loss[None] == value
    assert np.any(seed != 0.0)

    rng = np.random.default_rng(40 + gi)
    g.adj_m.from_numpy(rng.standard_normal(seed.shape))  # ot_loss_reverse owns dL/dm_i: it overwrites it
    ot_loss_reverse(s, g)
    assert np.array_equal(g.adj_m.to_numpy(), seed)

    # the Tape oracle's way (mls_mpm/tape.py): ot_loss on the grad State's own masses leaves the seed, then the
    # taped pass differentiates seed_loss
    t.loss[None] = 0.0
    tg.m.fill(0.0)
    losses.splat(t, tg, f)
    losses.ot_loss(t, tg)
    assert rel_err(tg.seed.to_numpy(), seed) <= 1e-12
    tg.m.fill(0.0)
    with ti.ad.Tape(loss=t.loss):
        losses.splat(t, tg, f)
        losses.seed_loss(t, tg)
    tape_x = t.x.grad.to_numpy()[f]
    assert max_rel_err(g.adj_m.to_numpy(), tg.m.grad.to_numpy()) <= TOL

    b = pair.prefill(rng, ["adj_x"], {"adj_x": np.stack([tape_x] * 2)})
    splat_reverse(s, g, a, f)
    assert rel_err(a.adj_x.to_numpy()[f % 2] - b["adj_x"][f % 2], tape_x) <= TOL
    assert np.array_equal(a.adj_x.to_numpy()[1 - f % 2], b["adj_x"][1 - f % 2])


def test_evaluate_reverse_on_ot_and_mass_grids(ot_pair):
    """losses.evaluate on OTLoss grids (ot_loss on the transport grids, grid_loss on the eq 11 grid) and its twin
    evaluate_reverse (ot_loss_reverse or grid_loss_reverse, then splat_reverse on each) vs one Tape of splat and
    seed_loss / grid_loss over all three grids: dL/dx_p rel err <= 1e-8. The loss is sum_g w_g S_g (computed
    here with ot.sinkhorn_divergence) plus eq 11, rel err <= 1e-12."""
    pair, f = ot_pair, 3
    s, t, a = pair.s, pair.t, pair.a
    L = losses.evaluate(s, f)
    expected = 0.0
    for g, spec in zip(s.loss_grids, pair.specs):
        m = g.m.to_numpy()[..., 0]
        if g.kind == "ot":
            r = ot.sinkhorn_divergence(m, spec.target[..., 0], spec.blur / spec.res, spec.reach, tol=spec.tol)
            expected += spec.weight * r.value
        else:
            expected += 0.5 * spec.weight * np.sum((m - spec.target[..., 0]) ** 2)
    assert rel_err(L, expected) <= 1e-12

    t.loss[None] = 0.0
    for g, tg in zip(s.loss_grids, t.loss_grids):
        tg.m.fill(0.0)
        if g.kind == "ot":
            tg.seed.from_numpy(g.seed.to_numpy())
    with ti.ad.Tape(loss=t.loss):
        for tg in t.loss_grids:
            losses.splat(t, tg, f)
            if tg.kind == "ot":
                losses.seed_loss(t, tg)
            else:
                losses.grid_loss(t, tg)
    tape_x = t.x.grad.to_numpy()[f]
    pair.prefill(np.random.default_rng(41), ["adj_x"], {"adj_x": np.stack([tape_x] * 2)})
    evaluate_reverse(s, a, f)
    assert rel_err(a.adj_x.to_numpy()[f % 2], tape_x) <= TOL
    assert np.all(a.adj_x.to_numpy()[1 - f % 2] == 0.0)
