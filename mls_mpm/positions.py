"""Taichi's source positions, made without wrapping a caret line for every node of every kernel.

Taichi builds each kernel anew in every process, the offline cache notwithstanding: its Python front end walks the
kernel's syntax tree with every ti.func inlined, and gives each node a position (file, line, function, and the
source line with a line of carets under the node, wrapped to 80 columns by textwrap), which it keeps in case a
compile error must name it. The unrolled stencils of this package's kernels make about 150,000 such nodes in a
3D run, and the wrapping was most of the front end's time: the README's 3D example (sphere_to_torus_3d, warm Taichi
cache) took 14.3 s, of which about 4 s went into these strings (BENCHMARKS.md, "Kernel front end").

short_positions() replaces Taichi 1.7's ASTTransformerContext.get_pos_info with one that gives the same first line
(`File "...", line N, in func:`) and the node's first source line, as Taichi itself does on Python < 3.8, without
the carets. A compile error still names the file, line, function and source line. It changes nothing else: the
position is a message for errors only (Taichi's offline cache keys do not hold it, so cached kernels stay valid).

Applied only to Taichi 1.7 (setup.py asks for >= 1.7, < 1.8), whose method it was written against; the environment
variable MLS_MPM_TAICHI_POSITIONS=full keeps Taichi's own (carets and all). runtime.ensure calls it, before any
kernel of a Simulator, Renderer or Tape is built.
"""
import os

import taichi as ti
from taichi.lang.ast import ast_transformer_utils

from .errors import UserError

VARIABLE = "MLS_MPM_TAICHI_POSITIONS"
CHOICES = ("short", "full")
TAICHI = ast_transformer_utils.ASTTransformerContext.get_pos_info  # Taichi's own, as it was imported


def short_position(ctx, node):
    """The position of syntax-tree node `node` of the function ctx is building: Taichi's first line and the
    node's first source line."""
    return (f'File "{ctx.file}", line {node.lineno + ctx.lineno_offset}, in {ctx.func.func.__name__}:\n'
            f"{ctx.src[node.lineno - 1]}\n")


def applies() -> bool:
    """Whether short_positions changes anything here: on Taichi 1.7, with MLS_MPM_TAICHI_POSITIONS "short" or unset
    (or empty); "full" keeps Taichi's own, and any other value is refused."""
    choice = os.environ.get(VARIABLE) or "short"
    if choice not in CHOICES:
        raise UserError(f"environment variable {VARIABLE} = {choice!r}: expected one of {', '.join(CHOICES)}")
    return choice == "short" and tuple(ti.__version__[:2]) == (1, 7)


def short_positions():
    """Give Taichi's kernel front end short_position (module docstring), or Taichi's own back where
    MLS_MPM_TAICHI_POSITIONS=full (checked at every call, so that a change of the variable takes effect)."""
    ast_transformer_utils.ASTTransformerContext.get_pos_info = short_position if applies() else TAICHI
