"""Benchmark plumbing (the mls_mpm/bench subpackage, benchmarks/report.py) without timing anything: the tradeoff
rows (every setting that trades time for accuracy), the Pareto front, a row stopped at its time budget, the guide
computed from a sweep, options and output paths refused before anything is measured, and a GPU benchmark refused
where there is no GPU. The figures themselves are in BENCHMARKS.md.
"""
import csv
import importlib.util
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from mls_mpm import runtime
from mls_mpm.bench import against, bench_against, bench_gradient, gradient
from mls_mpm.bench.child import cpu_model
from mls_mpm.bench.tradeoff import FIELDS, _retry, measure, pareto, rows_for
from mls_mpm.cli import build_parser, main
from mls_mpm.runtime import ArchError
from mls_mpm.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
TORUS = ROOT / "scenes" / "circle_to_torus.toml"
TINY = ROOT / "tests" / "data" / "tiny.toml"


def report_module():
    spec = importlib.util.spec_from_file_location("report", ROOT / "benchmarks" / "report.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_full_sweep_has_every_setting():
    """Grid 32/64/128, particles per cell 1/4/9, stride 1/5/10/25, iterations 1/2/4/8 and converged, the three
    optimizers, multi-resolution loss grids, penalty, the other dtype: each row changes one setting only."""
    scene = load_scene(TORUS)  # 32^2, 16 per cell, stride 10, gd, 10 iterations, f64
    rows = {name: (group, ov) for name, group, ov in rows_for(scene, quick=False)}
    assert set(rows) == {"base", "n_grid=64", "n_grid=128", "ppc=1", "ppc=4", "ppc=9", "stride=1", "stride=5",
                         "stride=25", "iterations=1", "iterations=2", "iterations=4", "iterations=8", "converged",
                         "method=adam", "method=lbfgs", "grids=[16, 32]", "penalty=10", "f32"}
    assert rows["base"] == ("base", [])
    assert rows["stride=1"] == ("control stride", ["control.stride=1"])
    # a finer grid keeps the simulated time and dt below the CFL limit: 4x the steps at a quarter of dt
    n128 = dict(ov.split("=", 1) for ov in rows["n_grid=128"][1])
    assert (n128["sim.n_grid"], n128["sim.steps"], n128["control.stride"]) == ("128", "1200", "40")
    assert float(n128["sim.dt"]) == pytest.approx(scene.sim.dt / 4)
    quick = {name for name, _, _ in rows_for(scene, quick=True)}
    assert quick < set(rows) and "n_grid=128" not in quick and "iterations=4" not in quick
    assert all(ov[0] == "optimize.iterations=2" for _, _, ov in rows_for(scene, quick=True))


def row(name, t, q, status="ok"):
    return {"row": name, "wall_seconds": str(t), "loss_ratio": str(q), "status": status}


def test_pareto_front_keeps_only_undominated_rows():
    rows = [row("a", 1.0, 0.5), row("b", 2.0, 0.1), row("c", 3.0, 0.2), row("d", 2.0, 0.5), row("e", 0.5, 0.9),
            row("f", 0.1, 0.01, status="failed")]
    assert [r["row"] for r in pareto(rows)] == ["e", "a", "b"]  # c is beaten by b, d by a; f did not finish


def test_row_over_its_budget_is_stopped_and_marked(tmp_path):
    wall, summary, status = measure(TINY, "base", [], tmp_path / "run", max_seconds=0.5)
    assert summary is None and status == "stopped: over the 0.5 s budget of a row"
    assert 0.5 <= wall < 30.0
    assert not (tmp_path / "run" / "summary.json").exists()


def test_stopped_row_is_measured_again_only_with_a_larger_budget():
    stopped = row("converged", 300.0, "", status="stopped: over the 300 s budget of a row")
    assert _retry(stopped, 600) and _retry(stopped, None)  # None: no limit
    assert not _retry(stopped, 300) and not _retry(stopped, 120)
    assert not _retry(row("base", 10.0, 0.2), None) and not _retry(row("x", 1.0, 0.1, status="failed"), None)


def test_guide_ranks_rows_by_time_and_lists_stopped_ones(tmp_path):
    table = tmp_path / "tradeoff.csv"
    with open(table, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        w.writerow(dict(row("base", 10.0, 0.2), iou="0.8", overrides=""))
        w.writerow(dict(row("ppc=1", 5.0, 0.4), iou="0.7", overrides="sim.particles_per_cell=1"))
        w.writerow(dict(row("stride=5", 20.0, 0.1), iou="0.9", overrides="control.stride=5"))
        w.writerow(dict(row("n_grid=128", 300.0, "", status="stopped: over the 300 s budget of a row"),
                        overrides="sim.n_grid=128"))
    lines = report_module().guide(table).splitlines()[2:]
    assert [ln.split(" (")[0] for ln in lines] == ["| ppc=1", "| base", "| stride=5", "| n_grid=128"]
    assert "0.50x (5 s)" in lines[0] and "faster; worse: 2x the loss ratio" in lines[0]
    assert "slower; better: 0.5x the loss ratio" in lines[2] and "| reference |" in lines[1]
    assert "> 30x (> 300 s)" in lines[3] and "stopped: over the 300 s budget" in lines[3]


def test_bench_options_parse():
    p = build_parser()
    a = p.parse_args(["bench", "gradient", "--arch", "vulkan", "--out", "g.md"])
    assert (a.what, a.arch, a.out, a.max_seconds) == ("gradient", "vulkan", "g.md", None)
    a = p.parse_args(["bench", "gradient", "--against", "HEAD~3", "--repeats", "2", "--quick"])
    assert (a.against, a.repeats, a.quick) == ("HEAD~3", 2, True)
    a = p.parse_args(["bench", "tradeoff", "s.toml", "--max-seconds", "60"])
    assert (a.what, a.scene, a.arch, a.max_seconds) == ("tradeoff", "s.toml", "cpu", 60.0)


@pytest.mark.parametrize("argv, says", [
    (["bench", "scaling", "--arch", "gpu"], "bench scaling: --arch applies to bench gradient only; drop it"),
    (["bench", "tradeoff", "s.toml", "--arch", "vulkan"], "bench tradeoff: --arch applies to bench gradient only"),
    (["bench", "gradient", "--max-seconds", "60"], "bench gradient: --max-seconds 60: expected seconds > 0, with "
                                                   "bench tradeoff only"),
    (["bench", "tradeoff", "s.toml", "--max-seconds", "0"], "bench tradeoff: --max-seconds 0: expected seconds > 0"),
    (["bench", "tradeoff", "s.toml", "--max-seconds", "inf"], "bench tradeoff: --max-seconds inf: expected seconds > 0"),
    (["bench", "gradient", "s.toml"], "bench gradient: SCENE s.toml: a scene applies to bench tradeoff only; drop it"),
    (["bench", "scaling", "s.toml", "--quick"], "bench scaling: SCENE s.toml: a scene applies to bench tradeoff only"),
    (["bench", "scaling", "--against", "HEAD"], "bench scaling: --against applies to bench gradient only; drop it"),
    (["bench", "scaling", "--repeats", "2"], "bench scaling: --repeats applies to bench gradient only; drop it"),
    (["bench", "gradient", "--against", "HEAD", "--repeats", "0"],
     "bench: argument --repeats: expected an integer >= 1"),
])
def test_bench_options_that_do_not_apply_are_refused(argv, says, capsys):
    """One line, exit 2, before anything is measured (no scene is read: s.toml does not exist)."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mls-mpm: error: {says}") and len(err.splitlines()) == 1


def test_gpu_gradient_benchmark_refused_without_a_gpu(tmp_path, monkeypatch):
    if runtime._driver_present("cuda"):
        pytest.skip("a CUDA driver is installed here")
    monkeypatch.setenv("VK_ICD_FILENAMES", str(tmp_path / "no_driver.json"))
    with pytest.raises(ArchError, match=r"^sim.arch = gpu: no cuda or vulkan device .* use sim.arch = cpu$"):
        bench_gradient(quick=True, arch="gpu", out=tmp_path / "gpu.md", emit=lambda *_: None)
    assert not (tmp_path / "gpu.md").exists()


@pytest.fixture
def nothing_measured(monkeypatch):
    """Any benchmark child or backend probe fails the test: a refusal must come before them."""
    def child(*args, **kwargs):
        raise AssertionError("measured before the output path was checked")

    import mls_mpm.bench.child as child_module
    import mls_mpm.bench.scaling as scaling

    for module, name in [(gradient, "backend_here"), (gradient, "run_child"), (child_module, "run_child"),
                         (scaling, "run_child"), (against, "backend_here"), (against, "run_child")]:
        monkeypatch.setattr(module, name, child)


@pytest.mark.parametrize("argv, says", [
    (["bench", "gradient", "--out", "/proc/no_such_folder/t.md"],
     "--out /proc/no_such_folder/t.md: no such folder /proc/no_such_folder; create it first"),
    (["bench", "gradient", "--out", "/proc/t.md"], "--out /proc/t.md: folder /proc is not writable"),  # root too
    (["bench", "gradient", "--out", "."], "--out .: is a folder; expected a file name"),
    (["bench", "scaling", "--out", "/proc/figures"], "--out /proc/figures: cannot create the folder"),
    (["bench", "tradeoff", str(TINY), "--out", "/proc/sweep"], "--out /proc/sweep: cannot create the folder"),
])
def test_bench_output_refused_before_measuring(argv, says, capsys, nothing_measured):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"mls-mpm: error: {says}") and len(err.splitlines()) == 1, err


def test_bench_output_under_a_file_refused(tmp_path, capsys, nothing_measured):
    (tmp_path / "file").write_text("")
    assert main(["bench", "gradient", "--out", str(tmp_path / "file" / "t.md")]) == 2
    assert f"no such folder {tmp_path / 'file'}" in capsys.readouterr().err
    assert main(["bench", "scaling", "--out", str(tmp_path / "file")]) == 2
    assert "cannot create the folder (File exists)" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]  # no probe left behind


def test_bench_gradient_writes_out_after_the_check(tmp_path, monkeypatch):
    """A writable --out is accepted and the table lands there (children faked: nothing is timed); its first line
    says what the figures ran on, and that they were compiled fast where MLS_MPM_COMPILE says so."""
    monkeypatch.setenv("MLS_MPM_COMPILE", "fast")
    assert gradient.measured_on("cpu").startswith(f"Taichi CPU, 2 threads{gradient.FAST_COMPILE_NOTE}; CPU: ")
    monkeypatch.setenv("MLS_MPM_COMPILE", "optimized")
    monkeypatch.setattr(gradient, "backend_here", lambda arch: "cpu")
    fake = {"manual": {"forward_ms": 1.0, "backward_ms": 1.2, "peak_mib": 100.0, "backend": "cpu"},
            "tape": {"tape_ms": 4.4, "peak_mib": 200.0, "backend": "cpu"}}
    monkeypatch.setattr(gradient, "run_child",
                        lambda case, path, steps, tiny=False: dict(fake[path], **({"peak_mib": 40.0} if tiny else {})))
    out = tmp_path / "g.md"
    bench_gradient(quick=True, out=out, emit=lambda *_: None, dims=(2,))
    table = out.read_text().splitlines()
    cpu = f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs)"
    assert table[0].startswith(f"Taichi CPU, 2 threads; {cpu}. Memory:") and len(table) == 6
    assert table[4].endswith("| 1.000 | 8.19 M | 1.200 | 1.20 | 4.400 | 2.00 | 60 | 160 | 0.38 |")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.md"]
    # both dimensions: the 3D rows with their Tape, then the 3D / 2D throughput and the window's time
    bench_gradient(quick=True, out=out, emit=lambda *_: None)
    table = out.read_text().splitlines()
    rows = [line for line in table if line.startswith("| f32, 32^3 grid, 16384 particles")]
    assert len(rows) == 1
    assert rows[0].endswith("| 1.000 | 16.38 M | 1.200 | 1.20 | 4.400 | 2.00 | 60 | 160 | 0.38 |")
    assert any(line.startswith("3D forward particle-steps/s (f32, 32^3) / 2D (f32, 64^2), this run: 2.00") for line in table)
    assert any(line.startswith("One 10-step window of the 3D successor's settings (17157 particles, 32^3): forward + "
                               "manual backward 0.02 s") for line in table)


def test_bench_gradient_repeats_take_the_least_of_each_figure(tmp_path, monkeypatch):
    """repeats=3: a warm-up and three measured children per path and size; each figure the least of the three
    (children faked with figures that fall and rise: the least is not the first or the last run's)."""
    monkeypatch.setattr(gradient, "backend_here", lambda arch: "cpu")
    calls = []

    def child(case, path, steps, tiny=False):
        calls.append((path, tiny))
        k = [9.0, 3.0, 1.0, 2.0][(len(calls) - 1) % 4]  # warm-up, then 3 measured runs
        if path == "manual":
            return {"forward_ms": k, "backward_ms": 2 * k, "peak_mib": (40.0 if tiny else 100.0) + k, "backend": "cpu"}
        return {"tape_ms": 5 * k, "peak_mib": (80.0 if tiny else 200.0) + k, "backend": "cpu"}

    monkeypatch.setattr(gradient, "run_child", child)
    out = tmp_path / "g.md"
    bench_gradient(quick=True, out=out, emit=lambda *_: None, dims=(2,), repeats=3)
    assert len(calls) == 2 * 4 * 4  # 2 cases x (manual, tape, their tiny runs) x (warm-up + 3)
    table = out.read_text().splitlines()
    assert "Each figure: the least over 3 runs after a warm-up run." in table[0]
    assert table[4].endswith("| 1.000 | 8.19 M | 2.000 | 2.00 | 5.000 | 1.67 | 60 | 120 | 0.50 |")


def test_bench_gradient_on_a_gpu_runs_no_memory_children(tmp_path, monkeypatch):
    """On a GPU no memory is measured: neither the cache-filling warm-up child nor the tiny ones run (each child
    still excludes compile time by its own warm-up pass), only `repeats` children per path and case; the memory
    columns are dashes and the header names the backend."""
    monkeypatch.setattr(gradient, "backend_here", lambda arch: "cuda")
    monkeypatch.setattr(gradient, "_device_name", lambda backend: "a test GPU")
    calls = []

    def child(case, path, steps, tiny=False):
        calls.append((case["arch"], path, tiny))
        k = [3.0, 1.0][(len(calls) - 1) % 2]
        if path == "manual":
            return {"forward_ms": k, "backward_ms": 2 * k, "peak_mib": 100.0, "backend": "cuda"}
        return {"tape_ms": 5 * k, "peak_mib": 200.0, "backend": "cuda"}

    monkeypatch.setattr(gradient, "run_child", child)
    out = tmp_path / "g.md"
    bench_gradient(quick=True, arch="gpu", out=out, emit=lambda *_: None, dims=(2,), repeats=2)
    assert calls == [("gpu", "manual", False)] * 2 + [("gpu", "tape", False)] * 2 + \
        [("gpu", "manual", False)] * 2 + [("gpu", "tape", False)] * 2
    table = out.read_text().splitlines()
    assert table[0].startswith("Taichi cuda (a test GPU); CPU: ") and "Memory: not measured" in table[0]
    assert table[0].endswith("Each figure: the least over 2 runs.")
    assert table[4].endswith("| 1.000 | 8.19 M | 2.000 | 2.00 | 5.000 | 1.67 | - | - | - |")


def git(*args):
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True)


needs_git = pytest.mark.skipif(git("rev-parse", "--show-toplevel").returncode != 0, reason="not a git checkout")
TINY_CASE = {"tiny": dict(dtype="f32", n_grid=16, particles=64, steps=2)}  # at the tiny size: its own memory base


@pytest.fixture
def temp_here(tmp_path, monkeypatch):
    """tempfile's folder (where --against makes its worktree) is tmp_path, so that leftovers can be seen."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    return tmp_path


@needs_git
@pytest.mark.slow  # six children of about 3 s each
def test_against_head_measures_both_trees_alternately(temp_here):
    """Each child imports its own tree's mls_mpm; warm-ups, then old and new in turn; the table's ratios are those
    of its figures; the temporary worktree is gone afterwards, from the disk and from git's list."""
    lines, said = [], []
    out = temp_here / "against.md"
    (row,) = bench_against("HEAD", repeats=2, out=out, emit=lines.append, progress=said.append, cases=TINY_CASE)
    old = Path(row["runs"]["old"][0]["mls_mpm"]).parents[1]
    assert old.parent.parent == temp_here and old.parent.name.startswith("mls-mpm-against-")
    assert [r["mls_mpm"] for r in row["runs"]["old"]] == [str(old / "mls_mpm" / "__init__.py")] * 2
    assert [r["mls_mpm"] for r in row["runs"]["new"]] == [str(ROOT / "mls_mpm" / "__init__.py")] * 2
    assert [text.split(": ")[-1] for text in said] == [
        f"old ({old}), warm-up", f"new ({ROOT}), warm-up", f"old ({old}), repeat 1/2", f"new ({ROOT}), repeat 1/2",
        f"old ({old}), repeat 2/2", f"new ({ROOT}), repeat 2/2"]
    assert not old.exists() and sorted(temp_here.iterdir()) == [out]
    assert str(old) not in git("worktree", "list", "--porcelain").stdout

    head = git("rev-parse", "--short", "HEAD").stdout.strip()
    cpu = f"CPU: {cpu_model()} ({os.cpu_count()} logical CPUs)"
    note = gradient.FAST_COMPILE_NOTE if os.environ.get("MLS_MPM_COMPILE") == "fast" else ""  # conftest: fast
    assert lines[0].startswith(f"Taichi CPU, 2 threads{note}; {cpu}; old: HEAD = {head}; "
                               f"new: the working tree at {head}")
    assert lines[1].startswith("Each figure: the minimum over 2 runs of each, alternating old and new")
    assert [c.strip() for c in lines[3].strip("|").split("|")] == [
        "case", "old fwd ms/step", "new fwd ms/step", "fwd speed-up", "old bwd ms/step", "new bwd ms/step",
        "bwd speed-up", "old bwd / fwd", "new bwd / fwd", "old MiB", "new MiB"]
    cells = [c.strip() for c in lines[5].strip("|").split("|")]
    assert len(lines) == 6 and cells[0] == "f32, 16^2 grid, 64 particles, 2 steps"
    fwd_old, fwd_new, fwd_up, bwd_old, bwd_new, bwd_up, ratio_old, ratio_new = map(float, cells[1:9])
    assert fwd_old == pytest.approx(min(r["forward_ms"] for r in row["runs"]["old"]), abs=5e-4)
    assert bwd_new == pytest.approx(min(r["backward_ms"] for r in row["runs"]["new"]), abs=5e-4)
    assert fwd_up == pytest.approx(fwd_old / fwd_new, rel=0.01, abs=0.01)
    assert bwd_up == pytest.approx(bwd_old / bwd_new, rel=0.01, abs=0.01)
    assert (ratio_old, ratio_new) == pytest.approx((bwd_old / fwd_old, bwd_new / fwd_new), rel=0.01, abs=0.01)
    assert cells[9:] == ["0", "0"]  # the tiny case is its own baseline
    assert out.read_text().splitlines() == lines


@needs_git
@pytest.mark.parametrize("stop", ["ctrl-c", "sigterm"])
def test_against_removes_its_worktree_when_stopped(stop, temp_here, monkeypatch):
    trees = []

    def stopped(case, path, steps, tiny=False, tree=None):
        trees.append(tree)
        assert (tree / "mls_mpm" / "bench" / "child.py").is_file()
        if stop == "sigterm":
            os.kill(os.getpid(), signal.SIGTERM)
        raise KeyboardInterrupt

    monkeypatch.setattr(against, "run_child", stopped)
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit if stop == "sigterm" else KeyboardInterrupt) as e:
        bench_against("HEAD", cases=TINY_CASE, emit=lambda *_: None, progress=lambda *_: None)
    assert stop == "ctrl-c" or e.value.code == 143
    assert len(trees) == 1 and not trees[0].exists() and list(temp_here.iterdir()) == []
    assert str(trees[0]) not in git("worktree", "list", "--porcelain").stdout
    assert signal.getsignal(signal.SIGTERM) == previous


@needs_git
@pytest.mark.parametrize("rev, says", [
    ("no-such-rev", "no-such-rev: not a revision of the repository at {ROOT}; expected a commit, branch or tag"),
    ("-x", "-x: not a revision of the repository"),
    ("root", "{root}: revision {root10} has no mls_mpm/bench/child.py measure(case, path, steps) to run"),
])
def test_against_a_bad_revision_is_refused_before_measuring(rev, says, temp_here, capsys, nothing_measured):
    root = git("rev-list", "--max-parents=0", "HEAD").stdout.split()[0]
    rev = root if rev == "root" else rev
    worktrees = git("worktree", "list").stdout
    assert main(["bench", "gradient", f"--against={rev}"]) == 2
    err = capsys.readouterr().err
    says = says.format(ROOT=ROOT, root=root, root10=root[:10])
    assert err.startswith(f"mls-mpm: error: bench gradient --against {says}") and len(err.splitlines()) == 1, err
    assert list(temp_here.iterdir()) == [] and git("worktree", "list").stdout == worktrees


@needs_git
def test_against_output_refused_before_the_worktree(temp_here, capsys, nothing_measured):
    assert main(["bench", "gradient", "--against", "HEAD", "--out", "/proc/t.md"]) == 2
    assert "--out /proc/t.md: folder /proc is not writable" in capsys.readouterr().err
    assert list(temp_here.iterdir()) == []


@needs_git
def test_against_table_takes_the_least_of_each_tree(temp_here, monkeypatch):
    """Children faked (nothing timed): the figures are each tree's minimum over its measured runs (the warm-up's
    are left out), memory is the least peak less that of the tiny size's measured run, and the ratios follow."""
    calls = []

    def child(case, path, steps, tiny=False, tree=None):
        name = "new" if tree == against.ROOT else "old"
        calls.append((name, tiny))
        n = sum(c == (name, tiny) for c in calls)  # 1: the warm-up
        fwd, bwd = {"old": (2.0, 3.0), "new": (1.0, 2.0)}[name]
        slower = 10.0 if n == 1 else 1.0 + n / 10  # the warm-up is far slower, later runs a little
        peak = (150.0 if tiny else {"old": 400.0, "new": 300.0}[name]) + (100.0 if n == 1 else n)
        return {"forward_ms": fwd * slower, "backward_ms": bwd * slower, "peak_mib": peak, "backend": "cpu",
                "mls_mpm": str(tree / "mls_mpm" / "__init__.py")}

    monkeypatch.setattr(against, "run_child", child)
    lines = []
    case = {"c": dict(dtype="f64", n_grid=32, particles=1245, steps=200)}
    bench_against("HEAD", repeats=3, quick=True, emit=lines.append, progress=lambda *_: None, cases=case)
    assert calls == [("old", False), ("new", False)] * 4 + [("old", True), ("new", True)] * 2
    # old: fwd 2 * 1.2, bwd 3 * 1.2, 402 - 152 MiB; new: fwd 1.2, bwd 2 * 1.2, 302 - 152 MiB
    assert lines[-1] == ("| f64, 32^2 grid, 1245 particles, 40 steps | 2.400 | 1.200 | 2.00 | 3.600 | 2.400 | 1.50 | "
                         "1.50 | 2.00 | 250 | 150 |")
    assert list(temp_here.iterdir()) == []


def test_bench_children_compile_as_this_process_resolved(monkeypatch):
    """Every benchmark child is told the compile mode explicitly (an older tree whose own default differs then
    compiles alike), and --against says when REV predates MLS_MPM_COMPILE and so cannot."""
    from mls_mpm.bench import child as child_module

    seen = {}

    def fake_run(cmd, env=None, **kwargs):  # subprocess.run is the module's: record only run_child's call
        if cmd[:2] == [sys.executable, "-c"]:
            seen.update(env)
        return subprocess.CompletedProcess(cmd, 0, stdout='{"mls_mpm": "x"}\n{"forward_ms": 1.0}\n', stderr="")

    monkeypatch.setattr(child_module.subprocess, "run", fake_run)
    for mode, expected in ((None, "fast"), ("optimized", "optimized")):
        if mode is None:
            monkeypatch.delenv("MLS_MPM_COMPILE", raising=False)
        else:
            monkeypatch.setenv("MLS_MPM_COMPILE", mode)
        child_module.run_child("small", "manual", 2)
        assert seen["MLS_MPM_COMPILE"] == expected
    assert against._compile_note("HEAD", "HEAD", "cpu") == ""  # HEAD reads the variable
    old_config = subprocess.CompletedProcess([], 0, stdout="SERIAL_BELOW = 4000\n", stderr="")
    monkeypatch.setattr(against, "_git", lambda *args: old_config)
    assert against._compile_note("abc", "d156786", "cpu") == ""  # optimized here: both trees compile optimized
    monkeypatch.setenv("MLS_MPM_COMPILE", "fast")
    assert against._compile_note("abc", "d156786", "cpu") == (
        "; d156786 predates MLS_MPM_COMPILE and compiles optimized, the working tree fast: "
        "MLS_MPM_COMPILE=optimized compares like with like")
    assert against._compile_note("abc", "d156786", "cuda") == ""  # a GPU compiles optimized in every tree


LOOP_ROWS = ["forward() (whole pass)", "backward() (whole pass)", "forward: stress + P2G + check", "forward: grid",
             "forward: G2P", "reverse: grid", "reverse: stress + P2G + check, G2P of the step before"]


def test_loop_profile_times_every_loop_of_a_step():
    """benchmarks/loop_profile.py runs each loop of the serial schedule's step (the real step bodies, imported from
    mls_mpm.step, mls_mpm.transfer and adjoint/) and prints one row of ms per step for each, all positive."""
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "loop_profile.py"), "--case", "small",
                          "--steps", "4", "--repeats", "1"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "TI_LOG_LEVEL": "error"})
    assert res.returncode == 0, res.stderr[-2000:]
    assert "f64, 32^2 grid, 1245 particles, 4 steps" in res.stdout
    rows = dict(line.strip("|").rsplit("|", 1) for line in res.stdout.splitlines()
                if line.startswith("| ") and not line.startswith("| loop"))
    assert [label.strip() for label in rows] == LOOP_ROWS
    assert all(float(ms) > 0 for ms in rows.values())


@pytest.mark.parametrize("script, argv, says", [
    ("loop_profile.py", ["--repeats", "0"], "--repeats 0: expected an integer >= 1"),
    ("loop_profile.py", ["--steps", "-2"], "--steps -2: expected an integer >= 1"),
    ("loop_profile.py", ["--case", "3d"], "invalid choice: '3d'"),
    ("dispatch_cost.py", ["--threads", "0"], "--threads 0: expected an integer >= 1"),
    ("dispatch_cost.py", ["--launches", "-1"], "--launches -1: expected an integer >= 1")])
def test_profile_scripts_refuse_bad_options(script, argv, says):
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *argv],
                         capture_output=True, text=True, cwd=ROOT)
    assert res.returncode == 2
    assert says in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("dim", [2, 3])
def test_bench_scene_in_cell_order_holds_the_same_particles_numbered_cell_by_cell(dim):
    """bench child scene_of(order="cell") (gpu_cases.py's sorted cases): the random case's particles, reordered so
    that the row-major cell index never decreases; everything else as in random order."""
    import numpy as np

    from mls_mpm.bench.child import scene_of

    case = dict(dim=dim, dtype="f32", n_grid=16, particles=500, steps=4)
    cfg, x_random, _, controls = scene_of(case, 4)
    cfg_c, x_cell, _, controls_c = scene_of(dict(case, order="cell"), 4)
    assert cfg_c == cfg and controls_c.shape == controls.shape
    cells = np.ravel_multi_index(tuple(np.floor(x_cell * 16).astype(int).T), (16,) * dim)
    assert np.all(np.diff(cells) >= 0)
    assert not np.all(np.diff(np.ravel_multi_index(tuple(np.floor(x_random * 16).astype(int).T), (16,) * dim)) >= 0)
    np.testing.assert_array_equal(np.sort(x_cell.view([("", x_cell.dtype)] * dim), axis=0),
                                  np.sort(x_random.view([("", x_random.dtype)] * dim), axis=0))


def test_dispatch_cost_times_the_same_loop_five_ways():
    """benchmarks/dispatch_cost.py times the real G2P loop serially, as a parallel range-for, pinned to one CPU, many
    times in one launch, and an empty parallel loop: one row each, all positive, the empty loop the cheapest."""
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "dispatch_cost.py"), "--launches", "3",
                          "--repeats", "1"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "TI_LOG_LEVEL": "error"})
    assert res.returncode == 0, res.stderr[-2000:]
    assert "G2P of 8192 particles, f32, 64^2 grid" in res.stdout
    rows = [line.strip("|").rsplit("|", 1) for line in res.stdout.splitlines()
            if line.startswith("| ") and not line.startswith("| loop")]
    assert [label.strip().split(",")[0] for label, _ in rows] == [
        "serial loop", "parallel loop", "parallel loop", "one parallel launch running 3 passes in one worker",
        "empty parallel loop"]
    ms = [float(v) for _, v in rows]
    assert all(v > 0 for v in ms) and ms[-1] < min(ms[:-1])
