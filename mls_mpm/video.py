"""animation.mp4 from a folder of frames: H.264, yuv420p, through the ffmpeg binary that imageio-ffmpeg ships.

Frames are read back one at a time (RGB or RGBA PNGs; RGBA is composited on white, as the GIF is), padded with
white to even sides (yuv420p halves the chroma planes) and piped to ffmpeg, which writes a temporary file beside
the target that is renamed onto it only when ffmpeg has finished: the file is written atomically.
"""
import os
from pathlib import Path

import numpy as np
from PIL import Image

from .errors import UserError
from .frames import frame_paths, on_white, temp_path

FPS = 20  # frames per second, as animation.gif (frames.write_gif)
CODEC = "libx264"
PIX_FMT = "yuv420p"  # the pixel format players and editors all decode
CRF = 18  # x264's constant rate factor: visually lossless for flat-shaded renders


def even_size(width, height):
    """The frame size of the video: each side rounded up to an even number of pixels."""
    return width + width % 2, height + height % 2


def _padded(im, size):
    """An RGB frame as uint8 (H, W, 3), padded with white on the right and bottom to size (width, height)."""
    rgb = np.asarray(on_white(im))
    W, H = size
    if rgb.shape[0] > H or rgb.shape[1] > W:
        raise ValueError(f"{im.filename}: {rgb.shape[1]} x {rgb.shape[0]} pixels, larger than the first frame's "
                         f"{W} x {H}")
    if rgb.shape[:2] == (H, W):
        return np.ascontiguousarray(rgb)
    out = np.full((H, W, 3), 255, np.uint8)
    out[:rgb.shape[0], :rgb.shape[1]] = rgb
    return out


def write_mp4(frames_dir, path, fps=FPS):
    """Encode the frames of frames_dir (frame_NNNNN.png, in order) as an H.264 MP4 at path, atomically.

    Every frame is padded to the first frame's size rounded up to even sides. Returns the number of frames.
    """
    try:
        import imageio_ffmpeg
    except ImportError:  # a dependency of the package (setup.py), missing from a partial install
        raise UserError(f"{path}: writing MP4 needs the imageio-ffmpeg package, which is not installed here (pip "
                        "install imageio-ffmpeg); or set render.mp4 = false") from None

    paths = frame_paths(frames_dir)
    if not paths:
        raise FileNotFoundError(f"{frames_dir}: no frame_NNNNN.png files to encode")
    if fps <= 0:
        raise ValueError(f"fps = {fps}: expected fps > 0")
    with Image.open(paths[0]) as im:
        size = even_size(*im.size)
    path = Path(path)
    tmp = temp_path(path)
    writer = imageio_ffmpeg.write_frames(str(tmp), size, fps=fps, codec=CODEC, pix_fmt_out=PIX_FMT,
                                         macro_block_size=1, quality=None,
                                         output_params=["-crf", str(CRF), "-f", "mp4"])
    try:
        writer.send(None)  # start ffmpeg
        for p in paths:
            with Image.open(p) as im:
                writer.send(_padded(im, size))
        writer.close()
        os.replace(tmp, path)
    finally:
        writer.close()
        if tmp.exists():
            tmp.unlink()
    return len(paths)


def read_mp4(path):
    """(frame count, (width, height)) of a video as ffmpeg decodes it (for tests and checks)."""
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    count = sum(1 for _ in reader)
    return count, tuple(meta["size"])
