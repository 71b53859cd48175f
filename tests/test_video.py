"""animation.mp4 (mls_mpm/video.py): H.264 frames decoded back by the ffmpeg that imageio-ffmpeg ships."""
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from mls_mpm.frames import FrameWriter
from mls_mpm.video import even_size, read_mp4, write_mp4

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")


def decode(path, size):
    """Every frame of a video as uint8 (K, H, W, 3), decoded by ffmpeg to raw RGB."""
    raw = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], check=True, capture_output=True).stdout
    W, H = size
    return np.frombuffer(raw, np.uint8).reshape(-1, H, W, 3)


def grey_frames(out, shape, values, alpha=None):
    """Frames of one grey value each (alpha: a (H, W) uint8 channel for all of them); returns their folder."""
    writer = FrameWriter(out)
    for v in values:
        frame = np.full(shape + (3,), v, np.uint8)
        writer.write(frame if alpha is None else np.dstack([frame, alpha]))
    return writer.frames_dir


def test_even_size_rounds_odd_sides_up():
    assert even_size(63, 47) == (64, 48) and even_size(64, 48) == (64, 48)


def test_the_video_decodes_to_every_frame_at_even_size(tmp_path):
    values = [0, 60, 120, 180, 240]
    frames = grey_frames(tmp_path, (47, 63), values)  # odd sides: padded with white to 64 x 48
    path = tmp_path / "animation.mp4"
    assert write_mp4(frames, path) == 5
    assert read_mp4(path) == (5, (64, 48))
    video = decode(path, (64, 48)).astype(int)
    assert video.shape == (5, 48, 64, 3)
    inside = video[:, 4:-4, 4:-4].reshape(5, -1).mean(axis=1)  # away from the padding's chroma bleeding
    assert np.allclose(inside, values, atol=3), inside
    assert video[:, 4:-4, -1].min() > 200  # the padded column is white
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_transparent_frames_are_composited_on_white(tmp_path):
    alpha = np.zeros((32, 32), np.uint8)
    alpha[8:24, 8:24] = 255  # an opaque black square on a transparent background
    frames = grey_frames(tmp_path, (32, 32), [0, 0], alpha)
    path = tmp_path / "animation.mp4"
    write_mp4(frames, path)
    video = decode(path, (32, 32)).astype(int)
    assert video[:, 12:20, 12:20].max() < 12 and video[:, :4, :4].min() > 243


def test_a_failed_encoding_keeps_the_old_video(tmp_path):
    path = tmp_path / "animation.mp4"
    path.write_bytes(b"old")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no frame_NNNNN.png files"):
        write_mp4(tmp_path / "empty", path)
    frames = grey_frames(tmp_path / "run", (16, 16), [10, 20])
    Image.new("RGB", (32, 32)).save(frames / "frame_00002.png")  # larger than the first: refused mid-encoding
    with pytest.raises(ValueError, match=r"frame_00002\.png: 32 x 32 pixels, larger than the first frame's 16 x 16"):
        write_mp4(frames, path)
    assert path.read_bytes() == b"old"
    assert not [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_a_missing_imageio_ffmpeg_is_one_line_naming_the_fix(tmp_path, monkeypatch):
    """A partial install without imageio-ffmpeg (a dependency in setup.py): one UserError naming the file, the
    package and render.mp4 = false, not an ImportError from inside the encoder; nothing is written."""
    from mls_mpm.errors import UserError

    frames = grey_frames(tmp_path, (16, 16), [0, 128])
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # `import imageio_ffmpeg` raises
    path = tmp_path / "animation.mp4"
    with pytest.raises(UserError, match=r"animation\.mp4: writing MP4 needs the imageio-ffmpeg package, which is not "
                                        r"installed here \(pip install imageio-ffmpeg\); or set render\.mp4 = false$"):
        write_mp4(frames, path)
    assert not path.exists()
