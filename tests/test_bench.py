"""Benchmark plumbing (the mls_mpm/bench subpackage, benchmarks/report.py) without timing anything: the tradeoff
rows (every setting that trades time for accuracy), the Pareto front, a row stopped at its time budget, the guide
computed from a sweep, options and output paths refused before anything is measured, and a GPU benchmark refused
where there is no GPU. The figures themselves are in BENCHMARKS.md.
"""
import csv
import importlib.util
from pathlib import Path

import pytest

from mls_mpm import runtime
from mls_mpm.bench import bench_gradient, gradient
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
                         (scaling, "run_child")]:
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
    """A writable --out is accepted and the table lands there (children faked: nothing is timed)."""
    monkeypatch.setattr(gradient, "backend_here", lambda arch: "cpu")
    fake = {"manual": {"forward_ms": 1.0, "backward_ms": 1.2, "peak_mib": 100.0, "backend": "cpu"},
            "tape": {"tape_ms": 4.4, "peak_mib": 200.0, "backend": "cpu"}}
    monkeypatch.setattr(gradient, "run_child",
                        lambda case, path, steps, tiny=False: dict(fake[path], **({"peak_mib": 40.0} if tiny else {})))
    out = tmp_path / "g.md"
    bench_gradient(quick=True, out=out, emit=lambda *_: None, dims=(2,))
    table = out.read_text().splitlines()
    assert table[0].startswith(f"Taichi CPU, 2 threads; CPU: {gradient.cpu_model()}. Memory:") and len(table) == 6
    assert " x " in gradient.cpu_model()  # the model name and the number of logical CPUs
    assert table[4].endswith("| 1.000 | 8.19 M | 1.200 | 1.20 | 4.400 | 2.00 | 60 | 160 | 0.38 |")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.md"]
    # both dimensions: the 3D rows have no Tape (2D only), then the 3D / 2D throughput and the window's time
    bench_gradient(quick=True, out=out, emit=lambda *_: None)
    table = out.read_text().splitlines()
    rows = [line for line in table if line.startswith("| f32, 32^3 grid, 16384 particles")]
    assert len(rows) == 1 and "| - (2D only) | - | 60 | - | - |" in rows[0]
    assert any(line.startswith("3D forward particle-steps/s (f32, 32^3) / 2D (f32, 64^2), this run: 2.00") for line in table)
    assert any(line.startswith("One 10-step window of the 3D successor's settings (17157 particles, 32^3): forward + "
                               "manual backward 0.02 s") for line in table)
