"""numpy's BLAS on one thread while Taichi simulates: its idle threads would otherwise spin on the simulator's CPUs.

An OpenBLAS call (numpy's `@`, `dot`: the L-BFGS direction, the optimal-transport loss) wakes OpenBLAS's worker
threads, one per CPU, and after the call they keep spinning for a while before they sleep. The simulator's next pass
starts at once, on Taichi's worker threads, which are pinned one to each CPU (affinity.py), so the two pools share
the CPUs by the scheduler's time slices: on 2 CPUs an L-BFGS morph with the optimal-transport loss ran its forward
and reverse passes 1.4-1.9x slower than with OpenBLAS on one thread (the same final loss in the runs measured;
BENCHMARKS.md, "numpy's BLAS on one thread"), and in 3D the one-launch passes, whose barriers take a lane's absence
for other work holding the CPUs, gave up 7 of 9 forward passes. The BLAS work of this program is vectors of at most
a few million entries and small matrices, which one thread does in milliseconds.

single_thread() limits the BLAS libraries loaded now (threadpoolctl) and, through the environment, those loaded
later (scipy's own OpenBLAS) and those of child processes. runtime.ensure calls it every time, so whichever way
Taichi was started, a Simulator runs with it.
"""
import os

from threadpoolctl import threadpool_limits

# read by each BLAS library when it loads: OpenBLAS (numpy's, scipy's), MKL, BLIS
THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def single_thread():
    """Every BLAS library of this process, loaded or to be loaded, and of its children, on one thread."""
    for name in THREAD_VARIABLES:
        os.environ[name] = "1"
    threadpool_limits(limits=1, user_api="blas")
