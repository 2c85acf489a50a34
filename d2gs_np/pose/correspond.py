"""Correspondences of a whole video for the pose solver (docs/method.md §5).

Built on ``features.py``: every frame is detected once (SIFT by default, ORB or AKAZE by
``FeatureConfig.detector``; motion masks dilated and excluded from detection, so no match lies on
or next to a moving object), then every pair (k, k + g) for g in ``CorrespondConfig.gaps``
(consecutive frames and frames two apart by default) is matched with the ratio test and verified
by RANSAC on the fundamental matrix. A pair with fewer than ``min_pair_matches`` verified matches
is reported and skipped.

Computed once per scene: ``correspondences(...)`` with a ``cache_dir`` (the run folder) stores the
result as ``correspondences_<key>.npz``, the key a hash of the config and of the frames' pixels
and masks, so a resumed run or a second solver call reads it instead of matching again, and a
changed config or video never reads a stale file.

Points are in this project's pixel convention (centres at +0.5, docs/conventions.md §2).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2gs_np.pose.config import CorrespondConfig
from d2gs_np.pose.features import detect_features, match_keypoints

__all__ = ["PairMatches", "Correspondences", "correspondences", "cache_key"]

CACHE_PREFIX = "correspondences_"


@dataclass
class PairMatches:
    """Verified matches of frame ``k`` (``pts_k``) with frame ``j`` (``pts_j``), j > k."""

    k: int
    j: int
    pts_k: np.ndarray  # (M, 2) float64, our pixel convention
    pts_j: np.ndarray  # (M, 2)
    num_tentative: int  # ratio-test matches before RANSAC
    used: bool  # False: too few matches, skipped

    @property
    def num_matches(self) -> int:
        return int(self.pts_k.shape[0])

    @property
    def inlier_ratio(self) -> float:
        return self.num_matches / self.num_tentative if self.num_tentative else 0.0


@dataclass
class Correspondences:
    pairs: list  # list[PairMatches], every pair tried (used or skipped), ordered by (k, j)
    key: str  # cache key (config and frames)
    from_cache: bool = False

    @property
    def used(self) -> list:
        return [p for p in self.pairs if p.used]

    def report(self) -> list:
        """One line per pair: count, inlier ratio, and whether it was skipped."""
        lines = []
        for p in self.pairs:
            state = "used" if p.used else "skipped (too few matches)"
            lines.append(f"pair ({p.k}, {p.j}): {p.num_matches} matches of {p.num_tentative} tentative "
                         f"(inlier ratio {p.inlier_ratio:.2f}), {state}")
        return lines

    def to_arrays(self) -> dict:
        arrays = {"key": np.array(self.key)}
        meta = []
        for i, p in enumerate(self.pairs):
            arrays[f"pts_k/{i}"], arrays[f"pts_j/{i}"] = p.pts_k, p.pts_j
            meta.append([p.k, p.j, p.num_tentative, int(p.used)])
        arrays["meta"] = np.array(meta, dtype=np.int64).reshape(-1, 4)
        return arrays

    @classmethod
    def from_arrays(cls, arrays) -> "Correspondences":
        pairs = [PairMatches(int(k), int(j), np.asarray(arrays[f"pts_k/{i}"], dtype=np.float64),
                             np.asarray(arrays[f"pts_j/{i}"], dtype=np.float64), int(nt), bool(u))
                 for i, (k, j, nt, u) in enumerate(arrays["meta"])]
        return cls(pairs=pairs, key=str(arrays["key"]), from_cache=True)


def _check_inputs(images, masks):
    if not isinstance(images, (list, tuple)) or len(images) < 2:
        raise ValueError(f"images must be a list of >= 2 (H, W, 3) frames; got {type(images).__name__} of "
                         f"length {len(images) if hasattr(images, '__len__') else '?'}")
    if masks is None:
        masks = [None] * len(images)
    if len(masks) != len(images):
        raise ValueError(f"masks must hold one (H, W) bool mask (or None) per image: {len(images)}; got {len(masks)}")
    for i, (img, m) in enumerate(zip(images, masks)):
        img = np.asarray(img)
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"images[{i}] must have shape (H, W, 3); got {img.shape}")
        if m is not None and np.shape(m) != img.shape[:2]:
            raise ValueError(f"masks[{i}] must have the image's shape {img.shape[:2]}; got {np.shape(m)}")
    return list(masks)


def cache_key(images, masks, config: CorrespondConfig) -> str:
    """Hash (16 hex digits) of the config and of every frame's pixels and mask."""
    h = hashlib.sha256(json.dumps(dataclasses.asdict(config), sort_keys=True, default=list).encode())
    for img, m in zip(images, masks):
        a = np.ascontiguousarray(img)
        h.update(str((a.shape, a.dtype.str)).encode())
        h.update(a.tobytes())
        h.update(b"nomask" if m is None else np.packbits(np.asarray(m, dtype=bool)).tobytes())
    return h.hexdigest()[:16]


def correspondences(images, masks=None, config: CorrespondConfig = None, cache_dir=None) -> Correspondences:
    """Matches of every pair (k, k + g), g in ``config.gaps``, of a video (module docstring).

    images: list of (H, W, 3) frames, float in [0, 1] or uint8. masks: list of (H, W) bool motion
    masks (True = dynamic) or None. cache_dir: folder for the npz cache (None: no cache).
    """
    config = CorrespondConfig() if config is None else config
    if not isinstance(config, CorrespondConfig):
        raise TypeError(f"config must be a CorrespondConfig; got {type(config).__name__}")
    masks = _check_inputs(images, masks)
    key = cache_key(images, masks, config)
    path = None if cache_dir is None else Path(cache_dir) / f"{CACHE_PREFIX}{key}.npz"
    if path is not None and path.exists():
        with np.load(path) as z:
            return Correspondences.from_arrays({k: z[k] for k in z.files})
    fc = config.features
    kps = [detect_features(img, fc, m) for img, m in zip(images, masks)]
    pairs = []
    n = len(images)
    for k in range(n):
        for g in config.gaps:
            j = k + g
            if j >= n:
                continue
            fcj = fc
            if config.max_flow_fraction > 0:
                reach = config.max_flow_fraction * g * max(np.shape(images[k])[1], np.shape(images[j])[1])
                fcj = dataclasses.replace(fc, max_displacement_px=float(reach))
            m = match_keypoints(kps[k], kps[j], fcj)
            pairs.append(PairMatches(k, j, m.pts0, m.pts1, m.num_tentative, m.num_inliers >= config.min_pair_matches))
    pairs.sort(key=lambda p: (p.k, p.j))
    out = Correspondences(pairs=pairs, key=key)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **out.to_arrays())
        tmp.replace(path)
    return out
