"""Benchmarks behind `mls-mpm bench gradient | scaling | tradeoff | quality` (their figures are in BENCHMARKS.md).

    child.py     one measurement in a process of its own; the benchmark cases; probes of the backend, the CPU
    gradient.py  forward, manual backward and ti.ad.Tape speed and memory (`bench gradient`)
    against.py   a git revision and the working tree side by side (`bench gradient --against REV`)
    scaling.py   the same against particles, steps and grid, and scaling.png (`bench scaling`)
    tradeoff.py  accuracy against time over the settings of a scene, and tradeoff.png (`bench tradeoff`)
    quality.py   `mls-mpm morph` on the suite of shape pairs in scenes/images/pairs/ (`bench quality`)
    output.py    output paths proved writable before anything is measured; BenchError
"""
from .against import bench_against
from .child import backend_here
from .gradient import bench_gradient
from .output import BenchError
from .quality import bench_quality
from .scaling import bench_scaling
from .tradeoff import bench_tradeoff

__all__ = ["backend_here", "bench_against", "bench_gradient", "bench_quality", "bench_scaling", "bench_tradeoff",
           "BenchError"]
