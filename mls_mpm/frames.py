"""Writing rendered frames to disk: numbered PNGs, an animated GIF, comparison sheets and a loss plot (Pillow only).

A render writes its frames into frames.new/ beside the frames/ of the last one and swaps the folders only when
every frame is written (`swap_in`), so a render that fails or is interrupted leaves the old frames as they were
(`discard_new`). `recover` cleans what a killed render left before the next one starts. The same three work on
any sequence folder (`folder=`: the particles/ and meshes/ of a 3D run, export3d.py), each file of which a
`FrameWriter` writes atomically through its `save` function.

Frames are RGB, or RGBA where the background is transparent (render.background = "transparent"); what shows
them without an alpha channel (the GIF, the video, a sheet) composites them on white first (`on_white`).
"""
from __future__ import annotations

import math
import os
import re
import shutil
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

FRAME_NAME = "frame_{:05d}.png"
FRAME_RE = re.compile(r"^frame_(\d{5,})\.png$")
# zlib level of every PNG written here. Level 1 encodes a 512^2 frame about 2-3x faster than Pillow's default
# (6) for files about 1.5x larger (benchmarks/render_speed.py times FrameWriter.write); PNG stays lossless.
PNG_COMPRESS_LEVEL = 1
FRAMES_DIR = "frames"
NEW_DIR = "frames.new"  # the frames of a render in progress
OLD_DIR = "frames.old"  # the frames a finished render replaces, between the two renames of `swap_in`
TEMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.tmp$")  # `temp_path`: .NAME.PID.tmp beside NAME


def frame_paths(frames_dir, pattern=FRAME_RE):
    """The frame files of a directory (names matching pattern, group 1 the number), ordered by their number."""
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in frames_dir.iterdir() if (m := pattern.match(p.name))]
    return [p for _, p in sorted(found)]


def temp_path(path):
    """The temporary file beside path that this process writes before renaming it to path."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def _alive(pid):
    """Whether a process with this id runs (another user's counts too)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(folder, names):
    """Delete the `temp_path` files in folder for target names matching the regex names whose writing process
    has ended (killed before its rename); any other file is left alone."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        m = TEMP_RE.match(p.name)
        if m and names.match(m.group("name")) and p.is_file() and not _alive(int(m.group("pid"))):
            p.unlink(missing_ok=True)


def _folders(out_dir, folder):
    """(FOLDER, FOLDER.new, FOLDER.old) in out_dir: the finished sequence, the one being written, the one replaced."""
    out = Path(out_dir)
    return out / folder, out / f"{folder}.new", out / f"{folder}.old"


def recover(out_dir, folder=FRAMES_DIR, names=FRAME_RE):
    """Undo what a killed render left in out_dir: frames.old/ goes back to frames/ when the swap was cut
    between its renames (frames/ missing), else it is deleted; frames.new/ and stale temporaries of files
    named like names go. folder: the sequence folder (frames, particles, meshes)."""
    frames, new, old = _folders(out_dir, folder)
    if old.is_dir() and not frames.exists():
        os.replace(old, frames)
    shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(new, ignore_errors=True)
    remove_stale_temps(frames, names)


def swap_in(out_dir, folder=FRAMES_DIR):
    """Make out_dir/frames.new/ the frames/ folder: the old frames renamed away, the new renamed in, the old
    deleted. Returns the frames folder."""
    frames, new, old = _folders(out_dir, folder)
    if frames.exists():
        os.replace(frames, old)
    os.replace(new, frames)
    shutil.rmtree(old, ignore_errors=True)
    return frames


def discard_new(out_dir, folder=FRAMES_DIR):
    """Delete the frames of a render that did not finish (out_dir/frames.new/)."""
    shutil.rmtree(_folders(out_dir, folder)[1], ignore_errors=True)


def save_png(image, path):
    """Write a uint8 (H, W, 3) RGB or (H, W, 4) RGBA array to path atomically (`atomic_save`)."""
    image = _as_u8(image, channels=(3, 4))
    mode = "RGB" if image.shape[2] == 3 else "RGBA"
    return atomic_save(path, lambda tmp: Image.fromarray(image, mode).save(tmp, format="PNG",
                                                                          compress_level=PNG_COMPRESS_LEVEL))


def atomic_save(path, write):
    """Write a file atomically: write(tmp) writes a temporary file in the same folder (`temp_path`), which is
    then renamed onto path; on any failure the temporary file is deleted and path is left as it was."""
    path = Path(path)
    tmp = temp_path(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def on_white(im):
    """A Pillow image as RGB, an alpha channel composited on white (what a transparent frame looks like in the
    GIF and the video); an RGB image is returned as RGB unchanged."""
    if im.mode in ("RGBA", "LA") or (im.mode == "P" and "transparency" in im.info):
        im = im.convert("RGBA")
        return Image.alpha_composite(Image.new("RGBA", im.size, (255, 255, 255, 255)), im).convert("RGB")
    return im.convert("RGB")


class FrameWriter:
    """Writes out_dir/frames/frame_00000.png, frame_00001.png, ... one frame at a time, numbered without gaps.

    clear=True removes frame files left by an earlier run first; clear=False continues after the last one
    (to extend an animation, thesis 7.4). Each frame is written atomically; nothing is kept in memory.
    folder: the frame folder's name in out_dir (NEW_DIR for a render that `swap_in` will finish).
    name, pattern, save: another kind of numbered file (export3d.py's PLY sequences): its name with one {}
    for the number, the regex of such names (group 1 the number), and save(item, path), which writes one
    atomically.
    """

    def __init__(self, out_dir, clear=True, folder=FRAMES_DIR, name=FRAME_NAME, pattern=FRAME_RE, save=save_png):
        self.frames_dir = Path(out_dir) / folder
        self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.name, self.pattern, self.save = name, pattern, save
        existing = frame_paths(self.frames_dir, pattern)
        if clear:
            for p in existing:
                p.unlink()
            self.count = 0
        else:
            self.count = int(pattern.match(existing[-1].name).group(1)) + 1 if existing else 0

    def write(self, image):
        """Write the next frame (or item of the sequence) and return its path."""
        path = self.save(image, self.frames_dir / self.name.format(self.count))
        self.count += 1
        return path


def write_gif(frames_dir, path, max_size=256, fps=20):
    """Build an animated GIF from the frames of frames_dir, read back one at a time and downscaled so that
    neither side exceeds max_size. Only the downscaled, palettised frames are held (Pillow's GIF writer
    keeps them). Returns the number of frames written."""
    paths = frame_paths(frames_dir)
    if not paths:
        raise FileNotFoundError(f"{frames_dir}: no frame_NNNNN.png files to animate")
    if max_size < 1 or fps <= 0:
        raise ValueError(f"max_size = {max_size}, fps = {fps}: expected max_size >= 1 and fps > 0")

    def frames():
        for p in paths:
            with Image.open(p) as im:
                im = on_white(im)
                scale = min(1.0, max_size / max(im.size))
                if scale < 1.0:
                    im = im.resize((max(1, round(im.width * scale)), max(1, round(im.height * scale))),
                                   Image.Resampling.LANCZOS)
                yield im.quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)

    it = frames()
    first = next(it)
    atomic_save(path, lambda tmp: first.save(tmp, format="GIF", save_all=True, append_images=it,
                                             duration=round(1000 / fps), loop=0, optimize=False, disposal=1))
    return len(paths)


def sheet(images, labels, gap=8, label_height=20, background=255):
    """Images side by side (e.g. initial | middle | final | target), each with its label centered above it
    in Pillow's default font. Images of different heights are top-aligned. Returns uint8 (H, W, 3)."""
    images = [_as_u8(im) for im in images]
    labels = [str(s) for s in labels]
    if not images or len(images) != len(labels):
        raise ValueError(f"sheet: expected one label per image and at least one image, got {len(images)} images "
                         f"and {len(labels)} labels")
    height = label_height + max(im.shape[0] for im in images)
    width = sum(im.shape[1] for im in images) + gap * (len(images) - 1)
    canvas = Image.new("RGB", (width, height), (background,) * 3)
    draw = ImageDraw.Draw(canvas)
    font = ImageFont.load_default()
    x = 0
    for im, label in zip(images, labels):
        canvas.paste(Image.fromarray(im, "RGB"), (x, label_height))
        left, top, right, bottom = draw.textbbox((0, 0), label, font=font)
        tx = x + (im.shape[1] - (right - left)) // 2 - left
        ty = (label_height - (bottom - top)) // 2 - top
        draw.text((tx, ty), label, fill=(0, 0, 0), font=font)
        x += im.shape[1] + gap
    return np.asarray(canvas, dtype=np.uint8)


def loss_plot(losses, path, size=(640, 400), title="loss"):
    """A loss-vs-iteration PNG with a log-scale y axis, axes, ticks and labels, drawn with Pillow (plot.py).

    Non-finite and non-positive losses have no place on a log axis and are left out of the curve.
    Returns the path written.
    """
    from . import plot

    losses = np.asarray(losses, dtype=np.float64).ravel()
    it = np.arange(len(losses))
    keep = np.isfinite(losses) & (losses > 0)
    W, H = size
    left, right, top, bottom = 72, 20, 28, 46  # margins around the plot area, pixels
    pw, ph = W - left - right, H - top - bottom
    if pw < 10 or ph < 10:
        raise ValueError(f"size = {size}: too small for the plot")
    canvas = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    font = plot.font()

    if keep.any():
        lo, hi = np.log10(losses[keep].min()), np.log10(losses[keep].max())
    else:
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    y0, y1 = math.floor(lo), math.ceil(hi)  # whole decades bound the axis
    n_max = max(len(losses) - 1, 1)
    axes = plot.Axes(left, top, pw, ph, (0, n_max), (y0, y1))

    # y ticks: every decade, with 2x and 5x minor labels when the range spans at most two decades
    for v, label in plot.decade_ticks(y0, y1, (1, 2, 5) if y1 - y0 <= 2 else (1,)):
        axes.y_tick(draw, v, label, font, grid=(225, 225, 225) if v % 1 == 0 else (242, 242, 242))
    for k in plot.linear_ticks(n_max):  # at most about 8
        axes.x_tick(draw, k, str(k), font)
    axes.frame(draw)

    points = [axes.pt(i, math.log10(v)) for i, v, ok in zip(it, losses, keep) if ok]
    if len(points) > 1:
        draw.line(points, fill=(200, 30, 30), width=2)
    for p in points if len(points) <= 60 else points[-1:]:
        draw.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=(200, 30, 30))

    plot.text(draw, (left + pw / 2, H - 6), "iteration", font, anchor="md")
    plot.text(draw, (left + pw / 2, top / 2), f"{title} (log scale)", font, anchor="mm")
    plot.text(draw, (8, top + ph / 2), "loss", font, anchor="lm")
    path = Path(path)
    save_png(np.asarray(canvas), path)
    return path


def _as_u8(image, channels=(3,)):
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] not in channels:
        shapes = " or ".join(f"(H, W, {k})" for k in channels)
        raise ValueError(f"image: expected uint8 {shapes}, got {image.dtype} {image.shape}")
    return np.ascontiguousarray(image)
