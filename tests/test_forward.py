"""Forward simulation (thesis section 3 and 6.1, eq 8-9, 14-21): conservation, exact motions, the fixed-corotated
stress, and the errors the simulator and SimConfig raise."""
import itertools

import numpy as np
import pytest
import taichi as ti
from scipy.linalg import polar

import mls_mpm
from conftest import ball, blob, body, grid_velocity, random_controls, rel_err, scene_config
from mls_mpm.material import stress

pytestmark = pytest.mark.usefixtures("taichi_f64_module")


def rigid_velocity(x, omega=1.0, u=(0.3, -0.2, 0.1), center=(0.5, 0.5, 0.5)):
    """v = u + omega e_z x (x - center): a translation plus a rotation about z (2D: the first two axes)."""
    d = x.shape[1]
    r = x - np.asarray(center[:d])
    spin = np.zeros_like(x)
    spin[:, 0], spin[:, 1] = -r[:, 1], r[:, 0]
    return np.asarray(u[:d]) + omega * spin


def make_sim(cfg, x0):
    """A simulator, checked to run the schedule cfg asks for: "serial" (one launch, serial loops) or "parallel"
    (on a CPU: each thread scatters into its own private grid, "lanes", summed by the grid loop)."""
    sim = mls_mpm.Simulator(cfg, x0)
    if cfg.schedule == "parallel":
        assert sim.fields.lanes == cfg.lanes(len(x0)) >= 1
    else:
        assert cfg.serial(len(x0)) and sim.fields.lanes == 0
    return sim


@pytest.fixture(scope="module", params=[(2, "serial"), (2, "parallel"), (3, "parallel")],
                ids=["2d-serial", "2d-parallel", "3d-parallel"])
def free_sim(request):
    """No gravity, no drag, far from the walls: nothing external acts (walls start 3 cells from the edge; the
    disk spans [0.35, 0.65] and moves < 0.02 in 30 steps; the 3D ball [0.34, 0.66], 12 steps). Both schedules in
    2D; in 3D the parallel one (the serial one runs the same per-particle and per-node bodies)."""
    dim, schedule = request.param
    cfg = scene_config(dim=dim, gravity=(0.0,) * dim, gamma=0.0, schedule=schedule)
    return make_sim(cfg, body(dim))


def test_grid_mass_equals_particle_mass(free_sim):
    """sum_i m_i^n = sum_p m_p = N m_p at every step (eq 15; the B-spline weights sum to 1): rel err <= 1e-13."""
    sim = free_sim
    x0 = body(sim.dim)
    sim.set_initial(x0, v=rigid_velocity(x0))
    sim.forward(random_controls(sim.control_shape, 0.05, seed=4))
    total = sim.n_particles * sim.cfg.m_p
    grid_m = sim.fields.grid_mass()
    assert grid_m.shape[0] == sim.cfg.steps
    for f in range(sim.cfg.steps):
        assert rel_err(grid_m[f].sum(), total) <= 1e-13, f
    assert np.all(grid_m >= 0.0)


def test_momentum_is_conserved(free_sim):
    """Without gravity, drag and walls, sum_p m_p v_p^n is the same at every step n (eq 16-18: APIC with MLS
    forces exchanges momentum only between particles), and equals the grid momentum sum_i p_i^n (eq 16) and
    sum_i m_i v_i^n (eq 17). Internal forces are large here: random controls of size 0.05 and a spinning body.
    Tolerance: 1e-12 of sum_p m_p |v_p|."""
    sim = free_sim
    x0 = body(sim.dim)
    sim.set_initial(x0, v=rigid_velocity(x0))
    sim.forward(random_controls(sim.control_shape, 0.05, seed=5))
    m_p, T = sim.cfg.m_p, sim.cfg.steps
    P0 = m_p * sim.state(0)["v"].sum(axis=0)
    scale = m_p * np.linalg.norm(sim.state(0)["v"], axis=1).sum()
    grid_m = sim.fields.grid_mass()
    grid_p = sim.fields.grid_momentum()
    last_v = sim.fields.grid_v.to_numpy()[0]  # the forward's own v_i of its last step (one slot)
    grid_v = [grid_velocity(sim, f) for f in range(T)]
    assert np.array_equal(grid_v[T - 1], last_v)
    moved = 0.0
    nodes = tuple(range(sim.dim))  # the grid axes
    for f in range(T + 1):
        v = sim.state(f)["v"]
        P = m_p * v.sum(axis=0)
        assert np.linalg.norm(P - P0) <= 1e-12 * scale, f
        if f < T:
            assert np.linalg.norm(grid_p[f].sum(axis=nodes) - P) <= 1e-12 * scale, f
            assert np.linalg.norm((grid_m[f][..., None] * grid_v[f]).sum(axis=nodes) - P) <= 1e-12 * scale, f
        moved = max(moved, np.abs(v - sim.state(0)["v"]).max())
    assert moved > 0.1  # the velocities did change: the conservation is not trivial
    x = sim.state(T)["x"]
    lo, hi = 4 * sim.cfg.dx, 1 - 5 * sim.cfg.dx  # every stencil stayed off the wall zone (bound = 3)
    assert np.all((x > lo) & (x < hi))


def test_body_at_rest_stays_at_rest(free_sim):
    """F = I, v = 0, C = 0, zero controls, no gravity: P(I) = 0 (eq 9) so nothing moves: x^n = x^0 and
    v^n = 0 to 1e-12 at every step."""
    sim = free_sim
    x0 = body(sim.dim)
    sim.set_initial(x0)
    sim.forward(sim.zero_controls())
    for f in (1, sim.cfg.steps // 2, sim.cfg.steps):
        st = sim.state(f)
        assert np.abs(st["x"] - x0).max() <= 1e-12
        assert np.abs(st["v"]).max() <= 1e-12
        assert np.abs(st["F"] - np.eye(sim.dim)).max() <= 1e-12


@pytest.mark.parametrize("dim", [2, 3], ids=["2d", "3d"])
def test_free_fall_with_drag(dim):
    """F = I, zero controls, gravity g, drag gamma: the body falls as one, every particle exactly as
    v^{n+1} = (1 - dt gamma) v^n + dt g (eq 16-18 plus gravity), x^{n+1} = x^n + dt v^{n+1} (eq 21),
    with C = 0 and F = I (eq 19-20). Tolerance: 1e-12 absolute (velocities ~0.3, positions ~0.5); in 3D
    gravity has a component along every axis (the 12 steps reach a speed of ~0.1)."""
    cfg = scene_config(dim=dim, gamma=5.0, gravity=(1.5, -9.8, 0.7)[:dim])
    x0 = body(dim)
    sim = mls_mpm.Simulator(cfg, x0)
    sim.forward(sim.zero_controls())
    g = np.asarray(cfg.gravity)
    v = np.zeros(dim)
    x = x0.copy()
    for f in range(1, cfg.steps + 1):
        v = (1.0 - cfg.dt * cfg.gamma) * v + cfg.dt * g
        x = x + cfg.dt * v
        st = sim.state(f)
        assert np.abs(st["v"] - v).max() <= 1e-12, f
        assert np.abs(st["x"] - x).max() <= 1e-12, f
        assert np.abs(st["C"]).max() <= 1e-10, f
        assert np.abs(st["F"] - np.eye(dim)).max() <= 1e-12, f
    assert np.linalg.norm(v) > 0.1


# ------------------------------------------------------------------ one step against a numpy transcription
def spline(t):
    """Cubic B-spline N(t) (eq 1-2): |t|^3 / 2 - t^2 + 2/3 on |t| < 1, (2 - |t|)^3 / 6 on 1 <= |t| < 2."""
    t = np.abs(t)
    return np.where(t < 1, 0.5 * t ** 3 - t ** 2 + 2 / 3, np.where(t < 2, (2 - t) ** 3 / 6, 0.0))


def fixed_corotated(F, mu, lam):
    R, _ = polar(F)
    J = np.linalg.det(F)
    return 2 * mu * (F - R) + lam * (J - 1) * J * np.linalg.inv(F).T


def reference_step(cfg, st, F_pc):
    """Eq 14-21 with gravity, drag and walls, written from the thesis in numpy for any dimension d: grid (m, v) of
    the step and the particle state (x, v, C, F) of the next one. F_pc: the control acting at this step, or None."""
    n, dx, inv_dx, dt, m_p, d = cfg.n_grid, cfg.dx, cfg.inv_dx, cfg.dt, cfg.m_p, cfg.dim
    x, v, C, F = st["x"], st["v"], st["C"], st["F"]
    Fs = F + F_pc if F_pc is not None else F  # eq 8, 14
    P = np.stack([fixed_corotated(Fp, cfg.mu, cfg.lam) for Fp in Fs])
    G = -3 * inv_dx ** 2 * dt * cfg.vol * P @ np.swapaxes(Fs, 1, 2) + m_p * C  # eq 61
    base = np.floor(x * inv_dx).astype(int) - 1
    stencil = []
    for offset in itertools.product(range(4), repeat=d):  # the 4^d nodes around each particle
        node = base + offset
        dpos = node * dx - x  # x_i - x_p
        N = np.prod(spline(dpos * inv_dx), axis=1)  # eq 2: the product of the 1D weights
        stencil.append((tuple(node.T), dpos, N))
    grid_m, grid_p = np.zeros((n,) * d), np.zeros((n,) * d + (d,))
    for node, dpos, N in stencil:
        np.add.at(grid_m, node, N * m_p)  # eq 15
        mom = m_p * v * (1 - dt * cfg.gamma) + np.einsum("pab,pb->pa", G, dpos)  # eq 16
        np.add.at(grid_p, node, N[:, None] * mom)
    # eq 17 + gravity's impulse, guarded at empty nodes by m_eps = 1e-20 m_p (mls_mpm/grid.py free_velocity)
    grid_v = (grid_p + grid_m[..., None] * dt * np.asarray(cfg.gravity)) / (grid_m + 1e-20 * m_p)[..., None]
    index = np.indices((n,) * d)  # index[a]: each node's index along axis a
    low, high = index < cfg.bound, index > n - 1 - cfg.bound  # the wall zones, per axis
    if cfg.boundary == "sticky":
        grid_v[np.any(low | high, axis=0)] = 0.0
    else:
        into = [(low[a] & (grid_v[..., a] < 0)) | (high[a] & (grid_v[..., a] > 0)) for a in range(d)]
        for a in range(d):
            grid_v[..., a][into[a]] = 0.0
    v_new, C_new = np.zeros_like(v), np.zeros_like(C)
    for node, dpos, N in stencil:
        vi = grid_v[node]
        v_new += N[:, None] * vi  # eq 18
        C_new += 3 * inv_dx ** 2 * N[:, None, None] * np.einsum("pa,pb->pab", vi, dpos)  # eq 19
    F_new = (np.eye(d) + dt * C_new) @ Fs  # eq 20
    return grid_m, grid_v, {"x": x + dt * v_new, "v": v_new, "C": C_new, "F": F_new}  # eq 21


@pytest.mark.parametrize("dim, boundary, schedule", [(2, "slip", "serial"), (2, "sticky", "parallel"),
                                                     (3, "slip", "parallel"), (3, "sticky", "serial")])
def test_step_matches_thesis_equations(dim, boundary, schedule):
    """Three steps against reference_step, a numpy transcription of eq 14-21 plus gravity, drag (gamma = 5) and
    walls, in 2D and 3D under both schedules and both walls: the first step (control 0 acts), the first step of
    control 1 and a step between them (no control); rel err <= 1e-12 on grid mass and velocity and on the next x,
    v, C, F. The body starts near the floor moving down with random C and F, so the wall zone (3 cells) is hit
    within the first steps; in 3D gravity has a component along every axis."""
    gravity = (1.5, -9.8) if dim == 2 else (1.5, -9.8, 0.7)
    cfg = scene_config(dim=dim, gamma=5.0, gravity=gravity, boundary=boundary, schedule=schedule)
    if dim == 2:
        center = (0.45, 0.2)
        x0 = blob(center=center, radius=0.1)
    else:
        center = (0.45, 0.27, 0.5)
        x0 = ball(center=center, radius=0.12, particles_per_cell=1)
    rng = np.random.default_rng(12)
    N = len(x0)
    sim = make_sim(cfg, x0)
    sim.set_initial(x0, v=rigid_velocity(x0, omega=2.0, u=(0.5, -1.5, 0.3), center=center),
                    C=2.0 * rng.standard_normal((N, dim, dim)),
                    F=np.eye(dim) + 0.1 * rng.standard_normal((N, dim, dim)))
    controls = random_controls(sim.control_shape, 0.05, seed=13)
    sim.forward(controls)
    grid_m = sim.fields.grid_mass()
    steps = (0, cfg.stride // 2, cfg.stride)
    grid_v = {f: grid_velocity(sim, f) for f in steps}  # state(f + 1) below checks the step's own v_i too
    walled = 0
    for f in steps:
        k, acts = divmod(f, cfg.stride)
        m_ref, v_ref, nxt = reference_step(cfg, sim.state(f), controls[k] if acts == 0 else None)
        assert rel_err(grid_m[f], m_ref) <= 1e-12, f
        assert rel_err(grid_v[f], v_ref) <= 1e-12, f
        got = sim.state(f + 1)
        for key in ("x", "v", "C", "F"):
            assert rel_err(got[key], nxt[key]) <= 1e-12, (f, key)
        b = cfg.bound
        wall = np.zeros(grid_m[f].shape, bool)
        for a in range(dim):
            wall[(slice(None),) * a + (slice(None, b),)] = wall[(slice(None),) * a + (slice(-b, None),)] = True
        walled += np.count_nonzero(wall & (grid_m[f] > 1e-10 * cfg.m_p))
    assert walled > 0  # the walls took part


# ------------------------------------------------------------------ the material
@ti.kernel
def stress_kernel(Fs: ti.template(), out: ti.template(), mu: ti.f64, lam: ti.f64):
    for q in Fs:
        out[q] = stress(Fs[q], mu, lam)


def test_fixed_corotated_stress():
    """P(F) = 2 mu (F - R) + lam (J - 1) J F^{-T} (eq 9) with R from scipy's polar decomposition, for F with
    J > 0 (where the polar rotation is a proper rotation): rel err <= 1e-12; P(R) = 0 for any rotation R."""
    rng = np.random.default_rng(9)
    Fs = [np.eye(2) + 0.4 * rng.standard_normal((2, 2)) for _ in range(20)]
    Fs = [F for F in Fs if np.linalg.det(F) > 0.05]
    Fs += [1.3 * np.eye(2), np.array([[1.0, 0.8], [0.0, 1.0]])]
    t = 2.2
    rotation = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    Fs.append(rotation)
    mu, lam = 41.7, 27.8
    field = ti.Matrix.field(2, 2, ti.f64, shape=len(Fs))
    out = ti.Matrix.field(2, 2, ti.f64, shape=len(Fs))
    field.from_numpy(np.stack(Fs))
    stress_kernel(field, out, mu, lam)
    P = out.to_numpy()
    for q, F in enumerate(Fs[:-1]):
        R, _ = polar(F)
        J = np.linalg.det(F)
        expected = 2 * mu * (F - R) + lam * (J - 1) * J * np.linalg.inv(F).T
        assert rel_err(P[q], expected) <= 1e-12, q
    assert np.abs(P[-1]).max() <= 1e-12


# ------------------------------------------------------------------ errors
@pytest.mark.parametrize("schedule", ["serial", "parallel"])
def test_particle_leaving_the_grid_raises(schedule):
    """A particle thrown at -300 in x covers 0.3 of the domain in one step of dt = 1e-3 and lands outside the
    grid: SimulationError naming step 1 and that particle (index 17), not a neighbour; both schedules."""
    x0 = blob()
    x0 = np.insert(x0, 17, [0.2, 0.5], axis=0)  # alone: its stencil shares no node with the disk
    v0 = np.zeros_like(x0)
    v0[17] = (-300.0, 0.0)
    sim = make_sim(scene_config(gravity=(0.0, 0.0), schedule=schedule), x0)
    sim.set_initial(x0, v=v0)
    with pytest.raises(mls_mpm.SimulationError, match=r"step 1: particle 17 left the simulation grid"):
        sim.forward(sim.zero_controls())


def test_fault_hint_names_gravity_not_the_cfl():
    """dt well below the CFL limit, no controls, gravity 1e300: the particles blow up (or leave the grid) at step
    1, and the hint names gravity, with its numbers, instead of blaming the CFL condition."""
    cfg = scene_config(n_grid=16, steps=3, stride=3, gravity=(0.0, -1e300), schedule="serial")
    sim = mls_mpm.Simulator(cfg, blob(n_grid=16, radius=0.15))
    with pytest.raises(mls_mpm.SimulationError) as e:
        sim.forward(sim.zero_controls())
    msg = str(e.value)
    assert msg.startswith("step 1: particle "), msg
    assert "likely cause: gravity: |g| = 1e+300 for 1 steps gives a speed of 1e+297, above dx / dt = 62.5" in msg
    assert "CFL" not in msg and "\n" not in msg


def test_nan_control_raises(free_sim):
    """A NaN in F_pc is refused before any step runs: ValueError naming the control (and its step) and the
    particle."""
    c = free_sim.zero_controls()
    s = free_sim.cfg.stride
    c[1, 5, 0, 1] = np.nan
    with pytest.raises(ValueError, match=rf"control 1 \(step {s}\), particle 5 holds NaN"):
        free_sim.forward(c)
    c[1, 5, 0, 1] = 0.0
    c[2, 0, 1, 1] = np.inf
    with pytest.raises(ValueError, match=rf"control 2 \(step {2 * s}\), particle 0 holds NaN or Inf"):
        free_sim.forward(c)


@pytest.mark.parametrize("change, name", [
    (dict(steps=0), "steps"),
    (dict(dt=0.0), "dt"),
    (dict(dt=-1e-3), "dt"),
    (dict(dt=float("nan")), "dt"),
    (dict(nu=0.5), "nu"),
    (dict(nu=-0.1), "nu"),
    (dict(gamma=1000.0, dt=1e-3), "gamma \\* dt"),
    (dict(gamma=-1.0), "gamma"),
    (dict(stride=31, steps=30), "stride"),
    (dict(n_grid=9, bound=3), "n_grid"),
    (dict(boundary="periodic"), "boundary"),
    (dict(E=0.0), "E"),
    (dict(particles_per_cell=10 ** 30), "particles_per_cell"),
    (dict(threads=10 ** 30), "threads"),
    (dict(threads=-1), "threads"),
    (dict(dim=4), "dim"),
    (dict(dim=True), "dim"),
    (dict(dim=3, gravity=(0.0, -9.8)), "gravity"),
    (dict(gravity=(0.0, -9.8, 0.0)), "gravity"),
    (dict(gravity="down"), "gravity"),
])
def test_config_rejects_bad_values(change, name):
    """SimConfig refuses values the simulator cannot use, with a ConfigError naming the setting:
    steps = 0, dt <= 0 or NaN, nu outside [0, 0.5), gamma dt >= 1 (eq 16's factor 1 - dt gamma would flip sign),
    stride > steps, n_grid below config.min_n_grid(bound) (too few nodes inside the walls for a 4x4 stencil),
    particles_per_cell above MAX_PARTICLES_PER_CELL and threads above MAX_THREADS (10**30 would reach the
    allocator or Taichi), a dim other than 2 or 3, gravity without one number per axis."""
    with pytest.raises(mls_mpm.ConfigError, match=f"^{name} = "):
        mls_mpm.SimConfig(**{**dict(n_grid=32, steps=30, dt=1e-3, E=100.0), **change})


def test_config_accepts_the_limits():
    """The boundary values just inside the limits are accepted (a refusal off by one would show here)."""
    from mls_mpm.config import MAX_PARTICLES_PER_CELL, MAX_THREADS, min_n_grid
    mls_mpm.SimConfig(n_grid=min_n_grid(3), bound=3, steps=30, stride=30, dt=1e-3, E=100.0, nu=0.0, gamma=999.0)
    with pytest.raises(mls_mpm.ConfigError, match=rf"^n_grid = {min_n_grid(3) - 1}: expected an integer >= "):
        mls_mpm.SimConfig(n_grid=min_n_grid(3) - 1, bound=3, steps=30, stride=30, dt=1e-3, E=100.0)
    mls_mpm.SimConfig(n_grid=32, steps=30, dt=1e-3, E=100.0, particles_per_cell=MAX_PARTICLES_PER_CELL,
                      threads=MAX_THREADS)
    with pytest.raises(mls_mpm.ConfigError, match=rf"^threads = {MAX_THREADS + 1}: expected an integer in "
                                                  rf"\[0, {MAX_THREADS}\]$"):
        mls_mpm.SimConfig(threads=MAX_THREADS + 1)


def test_extruded_shape_matches_2d():
    """A 2D disk extruded along z into a slab of 23 particle layers one cell apart, run in 3D with each layer
    carrying its 2D particle's control (blockdiag(F_pc, 0)), gravity in the xy plane and drag, matches the 2D run
    of the disk on the slab's middle layer: x, y, v, C, F of the 2D run to rel err 1e-12 at steps 1 to 4.

    Why it must: layers spaced dx apart sum the cubic B-spline to 1 along z (partition of unity) and reproduce
    linear functions, so away from the slab's ends every 3D node holds dx times the 2D node's mass and momentum,
    and the 3D stress of blockdiag(F, 1) is the 2D stress in its xy block (the cofactor's xy block is the 2D
    cofactor). The free faces at the ends (11 cells from the middle) reach it through at most 4 cells of
    stencil a step (P2G 2, G2P 2), so the first steps are exact to round-off; measured: 2e-15 at steps 1-3 and
    7e-14 at step 4, where the ends' influence has arrived but is still at round-off (asserted up to step 4).
    """
    steps, stride, n = 4, 2, 32
    cfg2 = scene_config(n_grid=n, steps=steps, stride=stride, schedule="serial")
    cfg3 = scene_config(dim=3, n_grid=n, steps=steps, stride=stride, particles_per_cell=1,
                        gravity=(0.0, -9.8, 0.0), schedule="parallel")
    x2 = blob(n_grid=n)
    N2 = len(x2)
    layers = (4.5 + np.arange(23)) / n
    middle = 11
    x3 = np.concatenate([np.column_stack([x2, np.full(N2, z)]) for z in layers])
    c2 = random_controls((cfg2.n_controls, N2, 2, 2), 0.05, seed=9)
    c3 = np.zeros((cfg3.n_controls, len(x3), 3, 3))
    c3[:, :, :2, :2] = np.tile(c2, (1, len(layers), 1, 1))
    v2 = rigid_velocity(x2, u=(0.3, -0.2))
    sim2, sim3 = mls_mpm.Simulator(cfg2, x2), mls_mpm.Simulator(cfg3, x3)
    sim2.set_initial(x2, v=v2)
    sim3.set_initial(x3, v=np.column_stack([np.tile(v2, (len(layers), 1)), np.zeros(len(x3))]))
    sim2.forward(c2)
    sim3.forward(c3)
    mid = slice(middle * N2, (middle + 1) * N2)
    errors = []
    for f in range(1, steps + 1):
        a, b = sim2.state(f), sim3.state(f)
        err = max(rel_err(b["x"][mid, :2], a["x"]), rel_err(b["v"][mid, :2], a["v"]),
                  rel_err(b["C"][mid, :2, :2], a["C"]), rel_err(b["F"][mid, :2, :2], a["F"]))
        errors.append(err)
        assert err <= 1e-12, (f, err)
        assert np.abs(b["x"][mid, 2] - layers[middle]).max() <= 1e-14  # no motion along z in the middle


def test_config_defaults_by_dimension():
    """dim = 3 defaults gravity to (0, -9.8, 0) and V_p^0 to dx^3 / particles_per_cell; dim = 2 as before."""
    c2, c3 = mls_mpm.SimConfig(n_grid=32), mls_mpm.SimConfig(dim=3, n_grid=32, particles_per_cell=8)
    assert c2.gravity == (0.0, -9.8) and c3.gravity == (0.0, -9.8, 0.0)
    assert c2.vol == (1 / 32) ** 2 / 4 and c3.vol == (1 / 32) ** 3 / 8
