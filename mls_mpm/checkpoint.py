"""Atomic files (temp file + rename) and the checks of what is read back, so an interrupt loses nothing and a
damaged file is refused with one line.

Every file is written to a temp file `.<name>.<random>.tmp` beside it, then renamed over it: a reader sees the
old file or the new one, never a part. Files get mode 0666 minus the umask (0644 usually), like any file a
program creates; a write that fails (a full disk) leaves no temp file and raises OutputError naming the file.
"""
import json
import os
import tempfile
from pathlib import Path

import numpy as np
from .errors import UserError

TEMP_GLOB = ".*.tmp"  # temp files of atomic_write and frames.save_png; a killed process can leave them behind


class CheckpointError(UserError):
    """A result or checkpoint file is missing, corrupt or from another scene."""


class OutputError(UserError):
    """The output folder cannot be used, or a file in it cannot be written."""


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path, write):
    """Call write(file_object) on a temp file beside path, then rename it over path."""
    path = Path(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except OSError as e:
        _remove(tmp)
        raise OutputError(f"{path}: cannot write it ({e.strerror or e}); free some space or pick another --out") \
            from None
    except BaseException:
        _remove(tmp)
        raise


def _remove(tmp):
    if tmp is not None and os.path.exists(tmp):
        os.unlink(tmp)


def save_json(path, obj):
    atomic_write(path, lambda fh: fh.write((json.dumps(obj, indent=2, default=_plain) + "\n").encode()))


def save_npz(path, meta, arrays):
    """Arrays by name plus JSON-able meta data, in one .npz written atomically."""
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["meta"] = np.array(json.dumps(meta, default=_plain))
    atomic_write(path, lambda fh: np.savez(fh, **payload))


def load_npz(path, what, meta_only=False):
    """(meta, arrays) of a file written by save_npz; CheckpointError names the file when it is unusable.

    meta_only: read the meta data alone (arrays is then {}): a .npz member is read only when asked for."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such file; expected the {what} of a run")
    try:
        with np.load(path, allow_pickle=False) as data:
            names = ["meta"] if meta_only else data.files
            arrays = {k: data[k] for k in names}
        meta = json.loads(str(arrays.pop("meta")))
    except Exception as e:  # any decoding failure means the same thing to the user
        raise CheckpointError(f"{path}: not a readable {what} ({type(e).__name__}); delete it or re-run") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{path}: not a readable {what} (its meta data is not a table); delete it or re-run")
    return meta, arrays


KINDS = {"f": ("a float array", "f"), "i": ("an integer array", "iu")}


def check_array(path, arrays, name, kind, shape, what):
    """arrays[name] exists, has dtype kind "f" (float) or "i" (integer) and the shape (None: any length);
    else CheckpointError naming the file, the array and what was expected."""
    word, kinds = KINDS[kind]
    want = "(" + ", ".join("any" if n is None else str(n) for n in shape) + (",)" if len(shape) == 1 else ")")
    a = arrays.get(name)
    if a is None:
        raise CheckpointError(f"{path}: lacks the array {name} ({word} of shape {want}); not a {what} of this "
                              "scene; delete it or re-run")
    if a.dtype.kind not in kinds or a.ndim != len(shape) or any(n is not None and n != m
                                                                for n, m in zip(shape, a.shape)):
        raise CheckpointError(f"{path}: array {name} is {a.dtype} of shape {a.shape}: expected {word} of shape "
                              f"{want}; not a {what} of this scene; delete it or re-run")
    if kind == "f" and not np.all(np.isfinite(a)):
        raise CheckpointError(f"{path}: array {name} holds NaN or Inf: expected finite numbers; delete it or re-run")
    return a


def check_value(path, where, value, kind, what, length=None):
    """A meta data value of kind int, float, bool, str, floats (a list of numbers; `length` of them if given),
    ints (a list of integers >= 0) or table (a dict); else CheckpointError naming the file and the entry."""
    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    ok = {"int": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
          "float": number,
          "bool": lambda v: isinstance(v, bool),
          "str": lambda v: isinstance(v, str),
          "floats": lambda v: isinstance(v, list) and all(number(x) for x in v)
                              and (length is None or len(v) == length),
          "ints": lambda v: isinstance(v, list) and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0
                                                        for x in v),
          "table": lambda v: isinstance(v, dict)}[kind](value)
    if not ok:
        expected = {"int": "an integer >= 0", "float": "a number", "bool": "true or false", "str": "a string",
                    "floats": "a list of " + (f"{length} " if length is not None else "") + "numbers",
                    "ints": "a list of integers >= 0",
                    "table": "a table"}[kind]
        found = "nothing" if value is None else json.dumps(value, default=_plain)[:40]
        raise CheckpointError(f"{path}: {where} is {found}: expected {expected}; not a {what} of this scene; "
                              "delete it or re-run")
    return value


def _plain(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON-able: {type(v).__name__}")


def split_state(state):
    """An optimizer state dict -> (JSON-able meta, arrays)."""
    meta, arrays = {}, {}
    for k, v in state.items():
        (arrays if isinstance(v, np.ndarray) else meta)[k] = v
    return meta, arrays
