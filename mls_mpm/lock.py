"""One job at a time per output folder: an exclusive `fcntl.flock` on `<folder>/.lock`, held for the whole job.

A second `mls-mpm run` (or `render`) into a folder another one is using is refused with one line naming the
folder and the holder's PID, instead of the two overwriting each other's files. The lock is a property of the
open file, so the kernel drops it when its holder dies, even by SIGKILL: a stale `.lock` file never blocks.
"""
import contextlib
import errno
import fcntl
import os
from pathlib import Path

from .checkpoint import OutputError

LOCK_NAME = ".lock"


class FolderBusyError(OutputError):
    """Another process is running a job in the output folder."""


@contextlib.contextmanager
def folder_lock(out_dir, what):
    """Hold `<out_dir>/.lock` (the folder must exist) while the block runs; `what` names the job in the
    refusal ("run", "render"). The file holds the PID of its holder and is removed on release."""
    path = Path(out_dir) / LOCK_NAME
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as e:
            raise OutputError(f"{path}: cannot create the folder's lock file ({e.strerror or e})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            os.close(fd)
            if e.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            raise FolderBusyError(f"{out_dir}: another mls-mpm job is using this output folder{_holder(path)}; "
                                  f"wait for it to end or pick another folder for this {what}") from None
        # the holder before us may have removed the file after we opened it: then our lock guards nothing
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()} {what}\n".encode())
        yield path
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)  # while still holding the lock, so a waiting process re-checks (above)
        os.close(fd)


def _holder(path):
    """' (PID n, mls-mpm <job>)' from a held lock file, or '' when it cannot be read yet."""
    try:
        pid, what = path.read_text().split()
        return f" (PID {int(pid)}, mls-mpm {what})"
    except (OSError, ValueError):
        return ""
