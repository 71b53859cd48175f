"""mls_mpm.sources: Taichi's kernel front end reads each ti.func's source once per process, and gets the same text
as Taichi's own readers give."""
import inspect
import textwrap

from taichi.lang import kernel_impl

import mls_mpm
from adjoint import transfer as adjoint_transfer
from mls_mpm import kernels, material, runtime, sources


def test_the_suite_runs_with_the_remembering_readers():
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))
    assert kernel_impl.getsourcelines is sources.SOURCELINES
    assert kernel_impl.getsourcefile is sources.SOURCEFILE
    assert kernel_impl.textwrap.fill is sources.FILL


def test_a_function_is_read_once_and_its_kept_lines_cannot_be_changed():
    reads = []

    def read(func):
        reads.append(func)
        return ["line a\n", "line b\n"], 7

    lookup = sources.remembered(read)
    first = lookup(len)
    first[0].append("changed by a caller\n")
    assert lookup(len) == (["line a\n", "line b\n"], 7)
    assert lookup(print) == (["line a\n", "line b\n"], 7)
    assert reads == [len, print]


def test_the_text_taichi_parses_is_taichis_own():
    funcs = [kernels.node_N, kernels.slab_dN_add, material.polar_rotation, adjoint_transfer.p2g_slab_reverse]
    for taichi_func in funcs:
        func = taichi_func.func.func  # the Python function under @ti.func (decorated.func: its kernel_impl.Func)
        lines, start = sources.SOURCELINES(func)
        assert (lines, start) == sources.TAICHI.getsourcelines(func) == inspect.getsourcelines(func)
        assert sources.SOURCEFILE(func) == sources.TAICHI.getsourcefile(func) == inspect.getsourcefile(func)
        wrapped = [sources.WRAP.fill(line, tabsize=4, width=9999) for line in lines]
        assert wrapped == [textwrap.fill(line, tabsize=4, width=9999) for line in lines]
        assert sources.WRAP.dedent("\n".join(wrapped)) == textwrap.dedent("\n".join(wrapped))
        assert func in sources.SOURCELINES.answers
