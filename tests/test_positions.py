"""mls_mpm.positions: Taichi's kernel front end gives each syntax node a short position (no wrapped caret lines),
and a compile error still names the file, line, function and source line as Taichi's own does."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from taichi.lang.ast import ast_transformer_utils

import mls_mpm
from mls_mpm import positions, runtime
from mls_mpm.errors import UserError

ROOT = Path(__file__).resolve().parents[1]

# A kernel with an undefined name, compiled in a fresh process after runtime.ensure; prints what Taichi raised.
BROKEN_KERNEL = '''
import json
import taichi as ti
import mls_mpm
from mls_mpm import runtime
from taichi.lang.ast import ast_transformer_utils

runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))


@ti.kernel
def broken_kernel() -> ti.f64:
    total = 0.0
    total += no_such_name * 2.0
    return total


try:
    broken_kernel()
except Exception as e:
    message = str(e)
    print(json.dumps({"type": type(e).__name__, "message": message,
                      "positions_from": ast_transformer_utils.ASTTransformerContext.get_pos_info.__module__}))
'''


def compile_error(tmp_path, choice):
    script = tmp_path / "broken.py"
    script.write_text(BROKEN_KERNEL)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop(positions.VARIABLE, None)
    if choice is not None:
        env[positions.VARIABLE] = choice
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1]), str(script)


def test_a_compile_error_still_names_file_line_function_and_source(tmp_path):
    short, script = compile_error(tmp_path, None)
    full, _ = compile_error(tmp_path, "full")
    assert short["positions_from"] == "mls_mpm.positions" and full["positions_from"] == ast_transformer_utils.__name__
    assert short["type"] == full["type"] == "TaichiNameError"
    source = "    total += no_such_name * 2.0"
    where = f'File "{script}", line {BROKEN_KERNEL.splitlines().index(source) + 1}, in broken_kernel:'
    for result in (short, full):
        lines = result["message"].splitlines()
        assert where in lines and source in lines
        assert lines[lines.index(where) + 1] == source
    # Taichi's own adds a line of carets under the node; the short position does not
    assert any(set(line.strip()) == {"^"} for line in full["message"].splitlines())
    assert not any(set(line.strip()) == {"^"} for line in short["message"].splitlines())


def test_the_suite_runs_with_short_positions():
    runtime.ensure(mls_mpm.SimConfig(dtype="f64", arch="cpu"))
    assert ast_transformer_utils.ASTTransformerContext.get_pos_info is positions.short_position


def test_full_restores_taichis_own_and_other_values_are_refused(monkeypatch):
    try:
        monkeypatch.setenv(positions.VARIABLE, "full")
        positions.short_positions()
        assert ast_transformer_utils.ASTTransformerContext.get_pos_info is positions.TAICHI
        monkeypatch.setenv(positions.VARIABLE, "carets")
        with pytest.raises(UserError, match=r"^environment variable MLS_MPM_TAICHI_POSITIONS = 'carets': expected "
                                            r"one of short, full$"):
            positions.short_positions()
        monkeypatch.setenv(positions.VARIABLE, "")  # set but empty: the default
        positions.short_positions()
        assert ast_transformer_utils.ASTTransformerContext.get_pos_info is positions.short_position
    finally:
        monkeypatch.delenv(positions.VARIABLE, raising=False)
        positions.short_positions()
