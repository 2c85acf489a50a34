"""Atomic checkpoints: write to a temporary file in the same folder, fsync, then rename.

A rename within one file system is atomic, so a reader (or a crash) sees either
the old checkpoint or the new one, never a half-written file, and a finished
result is never lost.
"""
from __future__ import annotations

import io
import json
import os
import tempfile
from pathlib import Path

import numpy as np


def _atomic_write_bytes(path, data: bytes):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path, text: str):
    _atomic_write_bytes(path, text.encode("utf-8"))


def check_output_path(path, what, is_file=False):
    """Raise ValueError, before any work, if ``path`` (a folder, or a file with ``is_file``) cannot be
    written: it exists as the other kind, sits under a file, or its nearest existing folder is not
    writable (``os.access``). ``what`` names it in the message (a flag, e.g. "--out")."""
    p = Path(path)
    if p.exists() and p.is_dir() == is_file:
        if is_file:
            raise ValueError(f"{what} {p} is a folder; give the path of a file (in it or elsewhere)")
        raise ValueError(f"{what} {p} is a file, not a folder; choose a folder path (or remove the file)")
    if is_file and p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"{what} {p} is read-only; choose another path or make it writable (chmod u+w)")
    folder = p if p.is_dir() else p.parent
    while not folder.exists():  # the nearest existing ancestor: the folder that gets the new entries
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{what} {p} sits under {folder}, which is a file, not a folder; choose a path outside it")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{what} {p}: the folder {folder} is not writable; choose a writable location or fix its "
                         "permissions (chmod u+w)")


def save_checkpoint(path, arrays: dict, meta: dict):
    """Save named arrays (e.g. "params/static.means", "adam/m/static.means") and JSON metadata atomically."""
    buf = io.BytesIO()
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)
    np.savez(buf, **payload)
    _atomic_write_bytes(path, buf.getvalue())


def load_checkpoint(path):
    """Inverse of save_checkpoint: (arrays dict, meta dict). Clear error if missing or corrupt."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist; train first (d2gs train SCENE --out RUN)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files if k != "__meta__"}
            meta = json.loads(bytes(z["__meta__"]).decode("utf-8"))
    except Exception as e:  # zipfile/ValueError/KeyError: name the file, not NumPy's advice
        raise ValueError(_unreadable(path, e)) from e
    return arrays, meta


def load_checkpoint_meta(path) -> dict:
    """Only the metadata of a checkpoint (its step, seconds, ...), without reading the arrays: an
    .npz is a zip whose members are read on access. Same errors as ``load_checkpoint``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"checkpoint {path} does not exist; train first (d2gs train SCENE --out RUN)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return json.loads(bytes(z["__meta__"]).decode("utf-8"))
    except Exception as e:
        raise ValueError(_unreadable(path, e)) from e


def _unreadable(path, error):
    """The message for a checkpoint that np.load or its __meta__ cannot read. NumPy's own text would
    advise ``allow_pickle=True`` (unsafe on an untrusted file, and never needed for ours)."""
    if isinstance(error, KeyError):
        why = "it has no __meta__ record"
    elif isinstance(error, (json.JSONDecodeError, UnicodeDecodeError)):
        why = "its __meta__ record is not JSON"
    elif isinstance(error, IsADirectoryError):
        why = "it is a folder"
    else:
        why = "it is not an .npz archive of plain arrays: truncated, corrupt or written by another program"
    return f"checkpoint {path} is unreadable ({why}); delete it and retrain (d2gs train SCENE --out RUN)"
