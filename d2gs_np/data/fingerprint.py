"""What identifies a scene's training frames: their count, times, image sizes and a digest of
their pixels.

A run records them in its checkpoints (``train.trainer``); resuming it or evaluating it on a
scene checks that scene against the record, so a run is never continued or scored on other
frames. The folder a scene was loaded from is not part of its identity: a copy of the folder
(same frames) is the same scene.
"""
from __future__ import annotations

import hashlib

import numpy as np

DIGEST_PREFIX = "sha256:"


def image_digest(frames) -> str:
    """``sha256:<hex>`` over the training frames' images as loaded (shape, dtype and bytes of each,
    in order); the same folder, or a byte-identical copy, gives the same digest."""
    h = hashlib.sha256()
    for i, f in enumerate(frames):
        if f.image is None:
            raise ValueError(f"frame {i} ({f.file_path}) has no image loaded; load the scene with load_images=True")
        a = np.ascontiguousarray(f.image)
        h.update(f"{a.shape}{a.dtype.str}".encode())
        h.update(a.data)
    return DIGEST_PREFIX + h.hexdigest()


def scene_record(scene) -> dict:
    """The record of ``scene`` that ``differences`` compares: ``times`` (K,), ``sizes`` [(w, h)]
    and ``digest`` (``image_digest``)."""
    return {"times": [float(f.time) for f in scene.frames], "sizes": [(int(f.width), int(f.height))
                                                                     for f in scene.frames],
            "digest": image_digest(scene.frames)}


def differences(saved: dict, current: dict) -> list:
    """What differs between two scene records (``scene_record``), in words, the saved one named
    "the run's"; empty when they are the same scene. A record without a digest (``None``: a run
    from before digests were recorded) is compared on frame count, times and sizes only."""
    n0, n = len(saved["times"]), len(current["times"])
    if n0 != n:
        return [f"it has {n} frames, the run's scene {n0}"]
    out = []
    sizes = [i for i, (a, b) in enumerate(zip(saved["sizes"], current["sizes"])) if tuple(a) != tuple(b)]
    if sizes:
        i = sizes[0]
        (w0, h0), (w, h) = saved["sizes"][i], current["sizes"][i]
        out.append(f"frame {i} is {w}x{h} pixels, the run's {w0}x{h0}"
                   + (f" ({len(sizes) - 1} more frames differ in size)" if len(sizes) > 1 else ""))
    t0, t = np.asarray(saved["times"], dtype=np.float64), np.asarray(current["times"], dtype=np.float64)
    moved = np.flatnonzero(~np.isclose(t0, t, rtol=0.0, atol=1e-9))  # times are normalised to [0, 1]
    if moved.size:
        i = int(moved[0])
        out.append(f"frame {i} is at time {t[i]:.6g}, the run's at {t0[i]:.6g}")
    if not sizes and saved.get("digest") is not None and saved["digest"] != current["digest"]:
        out.append(f"its images differ (content digest {_short(current['digest'])}, the run's "
                   f"{_short(saved['digest'])})")
    return out


def _short(digest: str) -> str:
    return digest[len(DIGEST_PREFIX):][:12] if digest.startswith(DIGEST_PREFIX) else digest[:12]
