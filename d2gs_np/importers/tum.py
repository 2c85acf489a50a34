"""Camera trajectories in the TUM RGB-D format (``d2gs export-trajectory``; docs/dataset_format.md §10).

One line per pose, ``timestamp tx ty tz qx qy qz qw``: the camera's pose in the world, i.e.
**camera-to-world** (``world_T_cam = inv(cam_T_world)``): (tx, ty, tz) is the camera centre in
world coordinates and the unit quaternion (scalar last) rotates camera axes into world axes. TUM's
page defines the position and orientation "of the optical center ... with respect to the world
origin" but not the camera's axes; these are OpenCV's (x right, y down, z forward), those of ROS
optical frames and of the TUM files SLAM systems (ORB-SLAM, DROID-SLAM) write. ATE and RPE (as
TUM's and evo's tools compute them) do not depend on that choice: a fixed change of camera axes
cancels in relative poses and leaves the centres alone. Lines starting with ``#`` are comments.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from d2gs_np.geometry.quaternion import quat_to_rotmat, rotmat_to_quat
from d2gs_np.geometry.se3 import check_rigid, se3_inverse

__all__ = ["write_tum", "read_tum", "HEADER"]

HEADER = ("# timestamp tx ty tz qx qy qz qw: camera-to-world (camera centre and orientation in the world), "
          "OpenCV camera axes (x right, y down, z forward)\n")


def write_tum(path, timestamps, cam_T_world) -> Path:
    """Write poses ``cam_T_world`` (N, 4, 4) at ``timestamps`` (N,) as a TUM trajectory; floats
    as Python's shortest round-trip repr, so the file reads back exactly."""
    ts = np.asarray(timestamps, dtype=np.float64)
    T = np.asarray(cam_T_world, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or ts.shape != (T.shape[0],):
        raise ValueError(f"cam_T_world must be (N, 4, 4) with timestamps (N,); got {T.shape} and {ts.shape}")
    if not (np.all(np.isfinite(ts)) and np.all(np.isfinite(T))):
        raise ValueError("timestamps and poses must be finite")
    for k in range(len(T)):
        check_rigid(T[k], f"cam_T_world[{k}]")
    c2w = se3_inverse(T)
    q = rotmat_to_quat(c2w[:, :3, :3])  # (N, 4) wxyz
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(HEADER)
        for k in range(len(T)):
            row = [ts[k], *c2w[k, :3, 3], q[k, 1], q[k, 2], q[k, 3], q[k, 0]]
            fh.write(" ".join(repr(float(v)) for v in row) + "\n")
    return path


def read_tum(path):
    """(timestamps (N,), cam_T_world (N, 4, 4)) of a TUM trajectory file (comments skipped;
    commas accepted as separators, as evo accepts them)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"trajectory file {path} does not exist")
    rows = []
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        tok = s.replace(",", " ").split()
        try:
            if len(tok) != 8:
                raise ValueError
            rows.append([float(v) for v in tok])
        except ValueError:
            raise ValueError(f"{path} line {i}: expected 'timestamp tx ty tz qx qy qz qw'; got {s[:120]!r}") from None
    a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    c2w = np.tile(np.eye(4), (len(a), 1, 1))
    c2w[:, :3, :3] = quat_to_rotmat(a[:, [7, 4, 5, 6]])  # (qx qy qz qw) -> wxyz, normalised
    c2w[:, :3, 3] = a[:, 1:4]
    return a[:, 0], se3_inverse(c2w)
