"""The memory estimate counts what a Simulator really allocates, and what would not fit is refused up front,
naming the largest part and the scene key that sizes it.

The estimate is compared with the Taichi fields actually allocated (every field of the State, its LossGrids
and the AdjointState, or the Tape's grad-enabled State: shape x components x dtype size, doubled where the
field has a gradient). Its field part must agree to the byte (Taichi packs dense fields); the numpy
arrays made around the fields (targets, controls and their uploads) may add at most 60% on top in these
small scenes, whose controls are a large share.
"""
import math
import re

import numpy as np
import pytest
import taichi as ti
from taichi.lang.field import Field
from taichi.lang.matrix import MatrixField

import mls_mpm
from adjoint.state import AdjointState
from conftest import blob
from mls_mpm import runtime
from mls_mpm.config import ConfigError
from mls_mpm.memory import check_memory, estimate_bytes, loss_grid_shapes, parts
from mls_mpm.tape import tape_state

pytestmark = pytest.mark.usefixtures("taichi_f64_module")

NUMPY_AT_MOST = 0.6
SIZE = {ti.f64: 8, ti.f32: 4, ti.i64: 8, ti.i32: 4}


def field_bytes(*objects):
    """Bytes of every Taichi field held by these objects (and by the LossGrids in their lists), each field counted
    once however many lists hold it."""
    fields = {}

    def collect(obj):
        for value in vars(obj).values():
            if isinstance(value, list):
                for v in value:
                    if hasattr(v, "__dict__"):
                        collect(v)
            elif isinstance(value, Field):
                fields[id(value)] = value
    for obj in objects:
        collect(obj)
    total = 0
    for value in fields.values():
        components = value.n * value.m if isinstance(value, MatrixField) else 1
        copies = 2 if value.snode.ptr.has_adjoint() else 1
        total += copies * math.prod(value.shape) * components * SIZE[value.dtype]
    return total


def config(**changes):
    return mls_mpm.SimConfig(**{**dict(n_grid=16, steps=6, stride=3, dt=1e-3, E=100.0), **changes})


def scenes():
    rng = np.random.default_rng(0)
    x0 = blob(n_grid=16, radius=0.2)
    N = len(x0)
    t16, t24 = rng.uniform(0, 1e-3, (16, 16)), rng.uniform(0, 1e-3, (24, 24))
    return {
        "parallel (lanes), mass loss with alpha": (config(schedule="parallel"), x0, mls_mpm.MassLoss(
            [t16, t24], alpha=[None, rng.uniform(1, 2, (24, 24))])),
        "serial, color loss": (config(schedule="serial"), x0, mls_mpm.ColorLoss(
            [rng.uniform(0, 1e-3, (20, 20, 3))], colors=rng.uniform(0, 1, (N, 3)))),
        "parallel, position loss, no gravity": (config(schedule="parallel", gravity=(0.0, 0.0)), x0,
                                                mls_mpm.PositionLoss(x0 + 0.01)),
        "serial, ot loss: a transport grid and a mass grid": (config(schedule="serial"), x0, mls_mpm.OTLoss(
            [t16, t24], weights=[1.0, 0.0], mass_weights=[0.0, 2.0])),
    }


@pytest.mark.parametrize("name", list(scenes()))
def test_estimate_matches_the_fields_a_simulator_allocates(name):
    cfg, x0, loss = scenes()[name]
    sim = mls_mpm.Simulator(cfg, x0, loss=loss)
    adjoint = AdjointState(sim.fields, runtime.real(cfg.dtype))  # what backward() allocates
    actual = field_bytes(sim.fields, adjoint)
    position = isinstance(loss, mls_mpm.PositionLoss)
    ps = parts(cfg, len(x0), loss_grid_shapes(loss), position_loss=position)
    assert (sim.fields.lanes > 0) == any("per-thread" in p.what for p in ps)
    assert sum(p.field_bytes for p in ps) == actual
    total = estimate_bytes(cfg, len(x0), loss_grid_shapes(loss), position_loss=position)
    assert actual <= total <= (1 + NUMPY_AT_MOST) * actual


@pytest.mark.parametrize("name", list(scenes()))
def test_tape_estimate_matches_the_tape_fields(name):
    """gradient_tape's grad-enabled State (mls_mpm.tape.tape_state, built without running the Tape)."""
    cfg, x0, loss = scenes()[name]
    runtime.ensure(cfg)
    position = isinstance(loss, mls_mpm.PositionLoss)
    t = tape_state(cfg, len(x0), [loss])
    actual = field_bytes(t)
    ps = parts(cfg, len(x0), loss_grid_shapes(loss), position_loss=position, tape=True)
    assert sum(p.field_bytes for p in ps) == actual
    assert actual <= sum(p.bytes for p in ps) <= (1 + NUMPY_AT_MOST) * actual


@pytest.mark.parametrize("cfg, n, grids, names, lower", [
    (config(n_grid=4096, steps=200, stride=10, dt=1e-5), 1000, [],
     r"the grid states \(m, p\) of 200 steps on the 4096\^2 grid",
     "sim.n_grid or sim.steps"),
    (config(steps=200, stride=10), 1000, [(20000, 1, False)], r"the loss grids loss.grids = \[20000\]", "loss.grids"),
    (config(n_grid=64, steps=2000, stride=10), 10 ** 6, [(64, 1, True)],
     r"the particle states \(x, v, C, F\) of 2001 steps x 1000000 particles", "sim.steps or sim.particles_per_cell"),
], ids=["n_grid", "loss.grids", "steps"])
def test_refusal_names_the_largest_part_and_its_key(cfg, n, grids, names, lower):
    cfg = cfg.replace(max_memory_gb=1.0)
    need = estimate_bytes(cfg, n, grids) / 2 ** 30
    with pytest.raises(ConfigError) as e:
        check_memory(cfg, n, grids, where="scenes/big.toml: ")
    msg = str(e.value)
    assert msg.startswith(f"scenes/big.toml: the simulation needs about {need:.2f} GiB ") and "\n" not in msg
    assert "above the limit of 1 GiB" in msg
    assert re.search(rf"the largest part is {names} \(\d+\.\d\d GiB\): lower {re.escape(lower)}, use sim.dtype = f32, "
                     r"or raise sim.max_memory_gb$", msg), msg


def test_simulator_counts_its_loss_grids_before_allocating():
    """A limit the bare simulation fits but its 512^2 loss grid does not: refused in Simulator(), by the loss grid."""
    cfg, x0 = config(), blob(n_grid=16, radius=0.2)
    target = np.zeros((512, 512))
    bare = estimate_bytes(cfg, len(x0))
    with_grid = estimate_bytes(cfg, len(x0), loss_grid_shapes(mls_mpm.MassLoss([target])))
    assert with_grid > 2 * bare
    limit = cfg.replace(max_memory_gb=(bare + with_grid) / 2 / 2 ** 30)
    mls_mpm.Simulator(limit, x0)
    with pytest.raises(ConfigError, match=r"the largest part is the loss grids loss.grids = \[512\]"):
        mls_mpm.Simulator(limit, x0, loss=mls_mpm.MassLoss([target]))


def test_gradient_tape_checks_its_fields_before_allocating():
    cfg, x0 = config(), blob(n_grid=16, radius=0.2)
    loss = mls_mpm.MassLoss([np.zeros((16, 16))])
    own = estimate_bytes(cfg, len(x0), loss_grid_shapes(loss))
    tape = estimate_bytes(cfg, len(x0), loss_grid_shapes(loss), tape=True)
    sim = mls_mpm.Simulator(cfg.replace(max_memory_gb=(own + tape / 2) / 2 ** 30), x0, loss=loss)
    with pytest.raises(ConfigError, match=r"^the Tape's grad-enabled fields \(gradient_tape\) need"):
        sim.gradient_tape(sim.zero_controls())
    assert sim._tape_state is None


def test_max_memory_must_be_a_number():
    with pytest.raises(ConfigError, match="max_memory_gb"):
        mls_mpm.SimConfig(max_memory_gb=-1)
