"""Rendering a finished run (mls_mpm/render_run.py): options checked before anything is allocated or written,
new frames written beside the old ones and swapped in only when all are written, interrupts between frames,
leftovers of a killed render cleaned, and a result.npz refused when the folder's summary.json is of another run.

Scene: tests/data/tiny.toml (32 x 32 grid, ~300 particles, 20 steps, frames of 64 pixels every 5 steps: 5 frames),
optimized once (one gd iteration) for the whole module; each test renders a copy of its folder.
"""
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from mls_mpm import memory
from mls_mpm import render_run as render_run_module
from mls_mpm.errors import Interrupted, UserError
from mls_mpm.frames import FrameWriter, frame_paths
from mls_mpm.render_run import RenderError, render_run
from mls_mpm.run import run_scene
from mls_mpm.scene import RENDER_SIZE_MAX, RENDER_SIZE_MIN, load_scene
from mls_mpm.video import read_mp4

TINY = Path(__file__).parent / "data" / "tiny.toml"
FRAMES = [f"frame_{k:05d}.png" for k in range(5)]
OLD = 7  # frames of an earlier, longer render in the folder


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "tiny"
    run_scene(load_scene(TINY, ["optimize.iterations=1"]), out, emit=lambda *_: None, render=False)
    return out


@pytest.fixture
def folder(finished, tmp_path):
    """A copy of the finished run holding the OLD frames of an earlier render, distinct bytes each."""
    out = tmp_path / "run"
    shutil.copytree(finished, out)
    writer = FrameWriter(out)
    for k in range(OLD):
        writer.write(np.full((16, 16, 3), k, np.uint8))
    return out


def snapshot(frames_dir):
    return {p.name: p.read_bytes() for p in sorted(Path(frames_dir).iterdir())}


def assert_old_frames_kept(out, before):
    assert snapshot(out / "frames") == before
    assert not (out / "frames.new").exists() and not (out / "frames.old").exists()


@pytest.mark.parametrize("options, message", [
    (dict(every=-1), "--every -1: expected an integer number of steps >= 1"),
    (dict(every=0), "--every 0: expected an integer number of steps >= 1"),
    (dict(size=0), f"--size 0: expected an integer number of pixels between {RENDER_SIZE_MIN} and {RENDER_SIZE_MAX}"),
    (dict(size=-5), "--size -5: expected an integer number of pixels between"),
    (dict(size=8), "--size 8: expected an integer number of pixels between 16 and"),
    (dict(size=100000), "--size 100000: expected an integer number of pixels between 16 and 8192"),
    (dict(size=64.5), "--size 64.5: expected an integer"),
    (dict(mode="wireframe"), "--mode wireframe: expected one of mass, color, particles"),
])
def test_bad_options_are_refused_before_the_old_frames_are_touched(folder, options, message):
    before = snapshot(folder / "frames")
    with pytest.raises(RenderError) as e:
        render_run(folder, emit=lambda *_: None, **options)
    assert isinstance(e.value, UserError) and str(e.value).startswith(message) and "\n" not in str(e.value)
    assert_old_frames_kept(folder, before)


def test_a_bad_size_stored_in_the_result_is_named_by_its_key(folder):
    result = folder / "result.npz"
    with np.load(result) as data:
        arrays = dict(data)
    meta = json.loads(str(arrays["meta"]))
    meta["settings"]["render"]["size"] = 100000
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(result, **arrays)
    (folder / "summary.json").unlink()  # it names render.size = 64
    before = snapshot(folder / "frames")
    with pytest.raises(RenderError, match=r"^render\.size = 100000 in .*result\.npz: expected an integer number of "
                                          r"pixels between 16 and 8192"):
        render_run(folder, emit=lambda *_: None)
    assert_old_frames_kept(folder, before)


def test_a_renderer_above_the_free_memory_is_refused_before_allocating(folder, monkeypatch):
    free = 40 * 2 ** 20  # 40 MiB free: a 64-pixel renderer fits, a 2048-pixel one (~90 MiB) does not
    monkeypatch.setattr(memory, "available_bytes", lambda: free)
    before = snapshot(folder / "frames")
    with pytest.raises(RenderError, match=r"^--size 2048: the renderer needs about 0\.\d+ GiB"):
        render_run(folder, size=2048, emit=lambda *_: None)
    assert_old_frames_kept(folder, before)
    render_run(folder, emit=lambda *_: None)
    assert [p.name for p in frame_paths(folder / "frames")] == FRAMES


def test_a_run_renders_with_its_own_simulator_and_the_same_bytes(tmp_path, monkeypatch):
    """run_scene passes its Simulator to render_run, which re-simulates with it (Simulator.serves) instead of
    building a second one (whose kernels Taichi would build again); `mls-mpm render` alone builds one, and both write
    the same frames, byte for byte."""
    built = []

    class Counted(render_run_module.Simulator):
        def __init__(self, *args, **kwargs):
            built.append(args[0])
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(render_run_module, "Simulator", Counted)
    out = tmp_path / "tiny"
    run_scene(load_scene(TINY, ["optimize.iterations=1"]), out, emit=lambda *_: None)
    assert built == []
    frames = snapshot(out / "frames")
    assert sorted(frames) == FRAMES
    render_run(out, emit=lambda *_: None)
    assert len(built) == 1
    assert snapshot(out / "frames") == frames


def test_the_memory_check_counts_a_reused_simulator_only_against_a_budget(monkeypatch):
    """A renderer that fits in the free memory beside the run's own Simulator (reused: its fields are allocated, no
    longer free) passes, where a new Simulator would not fit beside it; under sim.max_memory_gb the reused one's
    fields count against the budget as a new one's would."""
    cfg = load_scene(TINY).sim
    n, size = 300, 64
    renderer = render_run_module.estimate_bytes(cfg.n_grid, n, size, "mass", 8)
    simulator = memory.estimate_bytes(cfg, n)
    monkeypatch.setattr(memory, "available_bytes", lambda: (renderer + simulator / 2) / 0.9)
    render_run_module._check_memory(cfg, n, size, "mass", None, "--size 64", new_simulator=False)
    with pytest.raises(RenderError, match=r"^--size 64: the renderer needs about .* beside the simulation's"):
        render_run_module._check_memory(cfg, n, size, "mass", None, "--size 64", new_simulator=True)
    budget = cfg.replace(max_memory_gb=(renderer + simulator / 2) / 2 ** 30)
    for new in (False, True):
        with pytest.raises(RenderError, match=r"sim\.max_memory_gb"):
            render_run_module._check_memory(budget, n, size, "mass", None, "--size 64", new_simulator=new)


def test_new_frames_replace_the_old_ones_only_when_all_are_written(folder):
    lines = []
    paths = render_run(folder, emit=lines.append)
    assert [p.name for p in paths] == FRAMES and sorted(os.listdir(folder / "frames")) == FRAMES
    assert {p.parent for p in paths} == {folder / "frames"}
    assert not (folder / "frames.new").exists() and not (folder / "frames.old").exists()
    assert lines[0] == f"rendering scene tiny from {folder / 'result.npz'}"
    for name in ("animation.gif", "sheet.png", "loss.png"):
        assert (folder / name).is_file()
    assert read_mp4(folder / "animation.mp4") == (5, (64, 64))  # every frame, at the frames' size
    assert not [p for p in folder.iterdir() if p.name.endswith(".tmp")]


class StopAfter:
    """should_stop that turns true after it has been asked `k` times (once per frame written)."""

    def __init__(self, k):
        self.k, self.asked = k, 0

    def __call__(self):
        self.asked += 1
        return self.asked > self.k


@pytest.mark.parametrize("k", [0, 3])
def test_an_interrupt_between_frames_keeps_the_old_frames(folder, k):
    before = snapshot(folder / "frames")
    stop = StopAfter(k)
    with pytest.raises(Interrupted, match="rendering interrupted; the old frames are kept"):
        render_run(folder, emit=lambda *_: None, should_stop=stop)
    assert stop.asked == k + 1  # polled before each frame, stopped before frame k
    assert_old_frames_kept(folder, before)
    for name in ("animation.gif", "sheet.png", "loss.png"):
        assert not (folder / name).exists()


def test_a_failure_while_writing_keeps_the_old_frames(folder, monkeypatch):
    calls = []

    def failing_write(self, image):
        calls.append(self.frames_dir)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")
        return real_write(self, image)

    real_write = FrameWriter.write
    monkeypatch.setattr(FrameWriter, "write", failing_write)
    before = snapshot(folder / "frames")
    with pytest.raises(RenderError, match=r"cannot write the frames \(No space left on device\)$"):
        render_run(folder, emit=lambda *_: None)
    assert calls[0] == folder / "frames.new"
    assert_old_frames_kept(folder, before)


def test_leftovers_of_a_killed_render_are_cleaned(folder):
    frames = folder / "frames"
    dead = 2 ** 22 + 1  # above Linux's largest pid: no process has it
    stale = [frames / f".frame_00003.png.{dead}.tmp", folder / f".sheet.png.{dead}.tmp"]
    alive = frames / f".frame_00004.png.{os.getpid()}.tmp"  # a live process may still be writing it
    other = [frames / "notes.tmp", frames / f".frame_0004.png.{dead}.tmp", folder / f".summary.json.{dead}.tmp"]
    for p in stale + [alive] + other:
        p.write_bytes(b"partial")
    (folder / "frames.new").mkdir()
    (folder / "frames.new" / "frame_00000.png").write_bytes(b"partial")
    before = {name: data for name, data in snapshot(frames).items() if name.startswith("frame_")}
    with pytest.raises(Interrupted):
        render_run(folder, emit=lambda *_: None, should_stop=lambda: True)
    assert not any(p.exists() for p in stale) and not (folder / "frames.new").exists()
    assert alive.exists() and all(p.exists() for p in other)
    assert {name: data for name, data in snapshot(frames).items() if name.startswith("frame_")} == before


def test_a_swap_cut_between_its_renames_is_undone(folder):
    """Killed after the old frames were renamed away and before the new ones were renamed in."""
    before = snapshot(folder / "frames")
    (folder / "frames").rename(folder / "frames.old")
    (folder / "frames.new").mkdir()
    with pytest.raises(Interrupted):
        render_run(folder, emit=lambda *_: None, should_stop=lambda: True)
    assert_old_frames_kept(folder, before)


@pytest.mark.parametrize("change, message", [
    (lambda s: s.update(scene="other"), "summary.json is of scene other, result.npz of scene tiny"),
    (lambda s: s["settings"]["sim"].update(E=99.0), "summary.json and result.npz differ in sim.E (99.0 vs 88.0)"),
])
def test_a_folder_mixing_two_runs_is_refused(folder, change, message):
    summary = json.loads((folder / "summary.json").read_text())
    change(summary)
    (folder / "summary.json").write_text(json.dumps(summary))
    before = snapshot(folder / "frames")
    with pytest.raises(RenderError) as e:
        render_run(folder, emit=lambda *_: None)
    assert str(e.value).startswith(f"{folder}: {message}") and "\n" not in str(e.value)
    assert_old_frames_kept(folder, before)


def test_scene_key_render_background_transparent_gives_frames_with_alpha(tmp_path):
    """render.background = "transparent" (a scene key): every frame is RGBA, its corners (no body) fully
    transparent and the body opaque; the sheet and the GIF stay on white."""
    from PIL import Image

    out = tmp_path / "clear"
    scene = load_scene(TINY, ["optimize.iterations=0", "render.background=transparent"])
    assert scene.render.background == "transparent" and scene.to_dict()["render"]["background"] == "transparent"
    run_scene(scene, out, emit=lambda *_: None, render=False)
    paths = render_run(out, emit=lambda *_: None)
    assert [p.name for p in paths] == FRAMES
    for path in paths:
        with Image.open(path) as im:
            assert im.mode == "RGBA"
            a = np.asarray(im)[..., 3]
        assert a[0, 0] == a[0, -1] == a[-1, 0] == a[-1, -1] == 0 and a.max() == 255
    with Image.open(out / "sheet.png") as im:
        assert im.mode == "RGB"


def test_gif_and_mp4_off_write_neither_and_remove_stale_ones(tmp_path):
    """render.gif = false and render.mp4 = false: the frames, sheet and loss plot are written, no animation, and an
    earlier render's animation.gif and animation.mp4 (of other frames) are removed."""
    out = tmp_path / "tiny"
    run_scene(load_scene(TINY, ["optimize.iterations=1", "render.gif=false", "render.mp4=false"]), out,
              emit=lambda *_: None, render=False)
    for name in ("animation.gif", "animation.mp4"):
        (out / name).write_bytes(b"an earlier render")
    render_run(out, emit=lambda *_: None)
    assert [p.name for p in frame_paths(out / "frames")] == FRAMES
    assert (out / "sheet.png").is_file() and (out / "loss.png").is_file()
    assert not (out / "animation.gif").exists() and not (out / "animation.mp4").exists()
