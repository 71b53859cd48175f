"""Memory of the preallocated fields is estimated and a scene that would not fit is refused before allocating."""
import numpy as np
import pytest

import mls_mpm
from mls_mpm.config import ConfigError
from mls_mpm.memory import estimate_bytes


def test_estimate_counts_every_stored_step():
    """(x, v, C, F) = 12 words per particle-step, (m, p, v) = 5 words per node-step, controls and their gradient
    4 + 4 words per particle per control, one step of adjoints (2 x 12 per particle, 5 per node)."""
    cfg = mls_mpm.SimConfig(n_grid=32, steps=100, stride=10, dtype="f32")
    N = 1000
    words = 101 * N * 12 + 100 * 32 * 32 * 5 + 2 * 10 * N * 4 + 2 * N * 12 + 32 * 32 * 5
    assert estimate_bytes(cfg, N) == 4 * words
    assert estimate_bytes(cfg.replace(dtype="f64"), N) == 8 * words


def test_simulator_refuses_fields_over_the_limit():
    cfg = mls_mpm.SimConfig(n_grid=32, steps=100, stride=10, max_memory_gb=0.001)
    x0 = np.full((20000, 2), 0.5)
    need = estimate_bytes(cfg, len(x0)) / 2 ** 30
    with pytest.raises(ConfigError, match=rf"need about {need:.2f} GiB .* above the limit of 0.001 GiB; lower sim.steps"):
        mls_mpm.Simulator(cfg, x0)


def test_max_memory_must_be_a_number():
    with pytest.raises(ConfigError, match="max_memory_gb"):
        mls_mpm.SimConfig(max_memory_gb=-1)
