"""Taichi's front end reads each ti.func's source once per process, not at every call site.

Taichi 1.7 builds every kernel anew in each process, the offline cache notwithstanding (positions.py), and each call
of a ti.func inside a kernel is built from that function's source: its kernel_impl reads the source with
inspect.getsourcelines (which tokenizes the file up to the function's end), passes every line through textwrap.fill
and parses it. The kernels of a 3D run make about 1,900 such calls to some 100 functions, so the same few sources
were read and re-wrapped 1,900 times: about 0.5 s of a warm 3D run (BENCHMARKS.md, "Kernel front end").

read_sources_once() gives Taichi's kernel_impl a getsourcefile and getsourcelines that remember each function's
answer, and a textwrap whose fill remembers each line's. The text Taichi parses is the same, so the kernels, their
positions in error messages and Taichi's offline cache keys are unchanged. Applied only to Taichi 1.7 (setup.py asks
for >= 1.7, < 1.8), whose kernel_impl it was written against. runtime.ensure calls it, before any kernel is built.
"""
import functools
import textwrap
import types

import taichi as ti
from taichi.lang import kernel_impl

TAICHI = types.SimpleNamespace(getsourcefile=kernel_impl.getsourcefile, getsourcelines=kernel_impl.getsourcelines,
                               textwrap=kernel_impl.textwrap)  # Taichi's own, as it was imported


def remembered(read):
    """read(func), called once per function; the answer is kept for the process (functions are few and live as
    long as their modules). A list answer is copied out, so that no caller can change the kept one."""
    answers = {}

    def lookup(func):
        if func not in answers:
            answers[func] = read(func)
        answer = answers[func]
        return (list(answer[0]), answer[1]) if isinstance(answer, tuple) else answer

    lookup.answers = answers
    return lookup


FILL = functools.lru_cache(maxsize=None)(textwrap.fill)  # a pure function of its line (and constant keywords)
WRAP = types.SimpleNamespace(fill=FILL, dedent=textwrap.dedent)  # what kernel_impl uses of textwrap
SOURCEFILE = remembered(TAICHI.getsourcefile)
SOURCELINES = remembered(TAICHI.getsourcelines)


def applies() -> bool:
    """Whether read_sources_once changes anything here: on Taichi 1.7 only."""
    return tuple(ti.__version__[:2]) == (1, 7)


def read_sources_once():
    """Give Taichi's kernel_impl the remembering readers (module docstring); idempotent."""
    if applies():
        kernel_impl.getsourcefile, kernel_impl.getsourcelines, kernel_impl.textwrap = SOURCEFILE, SOURCELINES, WRAP
