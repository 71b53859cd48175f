"""Memory of a simulation, estimated before anything is allocated, and the up-front refusal of what would not fit."""
from .config import ConfigError


def estimate_bytes(cfg, n_particles):
    """Bytes of a State's per-step fields plus one step of adjoints: (x, v, C, F) per particle step,
    (m, p, v) per grid step, the controls and their gradient."""
    word = 8 if cfg.dtype == "f64" else 4
    particle = (cfg.steps + 1) * n_particles * (2 + 2 + 4 + 4) + 2 * cfg.n_controls * n_particles * 4
    grid = cfg.steps * cfg.n_grid ** 2 * (1 + 2 + 2)
    adjoint = 2 * n_particles * 12 + cfg.n_grid ** 2 * 5
    return (particle + grid + adjoint) * word


def available_bytes():
    """Memory the system can still give (MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def check_memory(cfg, n_particles, grids=(), where=""):
    """Refuse, before allocating, fields that would not fit (cfg.max_memory_gb, else 90% of what is free).

    grids: (res, channels, has_alpha) of each loss grid; where: a prefix naming the scene file, or "".
    """
    need = estimate_bytes(cfg, n_particles)
    limit = cfg.max_memory_gb * 2 ** 30 if cfg.max_memory_gb else None
    if limit is None:
        free = available_bytes()
        limit = 0.9 * free if free else None
    if limit is not None and need > limit:
        raise ConfigError(f"{where}the preallocated fields need about {need / 2 ** 30:.2f} GiB for {cfg.steps} steps x "
                          f"{n_particles} particles on a {cfg.n_grid}^2 grid ({cfg.dtype}), above the limit of "
                          f"{limit / 2 ** 30:.3g} GiB; lower sim.steps, sim.n_grid or sim.particles_per_cell, use "
                          "dtype f32, or raise sim.max_memory_gb")
