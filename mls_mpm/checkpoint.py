"""Atomic files (temp file + rename) and the run checkpoint, so an interrupt loses nothing."""
import json
import os
import tempfile
from pathlib import Path

import numpy as np
from .errors import UserError


class CheckpointError(UserError):
    """A result or checkpoint file is missing, corrupt or from another scene."""


def atomic_write(path, write):
    """Call write(file_object) on a temp file beside path, then rename it over path."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def save_json(path, obj):
    atomic_write(path, lambda fh: fh.write((json.dumps(obj, indent=2, default=_plain) + "\n").encode()))


def save_npz(path, meta, arrays):
    """Arrays by name plus JSON-able meta data, in one .npz written atomically."""
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["meta"] = np.array(json.dumps(meta, default=_plain))
    atomic_write(path, lambda fh: np.savez(fh, **payload))


def load_npz(path, what):
    """(meta, arrays) of a file written by save_npz; CheckpointError names the file when it is unusable."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such file; expected the {what} of a run")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(str(arrays.pop("meta")))
    except Exception as e:  # any decoding failure means the same thing to the user
        raise CheckpointError(f"{path}: not a readable {what} ({type(e).__name__}); delete it or re-run") from None
    return meta, arrays


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
