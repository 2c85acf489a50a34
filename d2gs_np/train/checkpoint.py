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
    except Exception as e:  # zipfile/ValueError/KeyError: name the file
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it or retrain") from e
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
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it or retrain") from e
