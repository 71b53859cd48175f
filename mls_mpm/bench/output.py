"""Where a benchmark writes, proved writable before anything is measured (a sweep takes minutes to hours)."""
import os
import tempfile
from pathlib import Path

from ..errors import UserError


class BenchError(UserError):
    """A benchmark option that does not apply, or an output path that cannot be written."""


def _probe(folder, what):
    """Create and remove a file in folder, or BenchError naming `what` and the reason."""
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write_test.")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise BenchError(f"{what}: folder {folder} is not writable ({e.strerror or e}); pick another with --out") \
            from None


def writable_file(path, what="--out"):
    """path: a file to be written; its folder must exist and be writable, and path must not be a folder."""
    path = Path(path)
    folder = path.parent
    if path.is_dir():
        raise BenchError(f"{what} {path}: is a folder; expected a file name, e.g. {path / 'gradient.md'}")
    if not folder.is_dir():
        raise BenchError(f"{what} {path}: no such folder {folder}; create it first or pick another with --out")
    _probe(folder, f"{what} {path}")
    return path


def writable_folder(folder, what="--out"):
    """folder: created (with its parents) where missing, then proved writable."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise BenchError(f"{what} {folder}: cannot create the folder ({e.strerror or e}); pick another with --out") \
            from None
    _probe(folder, f"{what} {folder}")
    return folder
