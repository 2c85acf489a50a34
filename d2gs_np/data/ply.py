"""The standard 3DGS PLY layout, so common viewers open our scenes.

Binary little-endian vertex properties, float32: x y z, nx ny nz (zeros),
f_dc_0..2 (degree-0 SH coefficients: rgb = 0.5 + SH_C0 * f_dc), opacity (logit),
scale_0..2 (log), rot_0..3 (wxyz quaternion, as 3DGS stores it).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814  # degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
_PROPS = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
          "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _format_of(header_lines):
    """The format a PLY header declares ("ASCII", "binary big-endian", ...), for messages."""
    fmt = next((line.split()[1] for line in header_lines if len(line.split()) > 1 and line.split()[0] == "format"),
               None)
    names = {"ascii": "ASCII", "binary_big_endian": "binary big-endian"}
    return names.get(fmt, f"format {fmt!r}" if fmt else "unknown-format")


def write_ply(path, means, log_scales, quats, opacity_logits, colors):
    """Write Gaussians (N rows each) to ``path``; colors are plain RGB, converted to SH DC."""
    means = np.asarray(means, dtype=np.float64)
    n = means.shape[0]
    cols = [means, np.zeros((n, 3)), (np.asarray(colors, dtype=np.float64) - 0.5) / SH_C0,
            np.asarray(opacity_logits, dtype=np.float64).reshape(n, 1), np.asarray(log_scales, dtype=np.float64),
            np.asarray(quats, dtype=np.float64)]
    for c, name in zip(cols, ["means", "normals", "colors", "opacity_logits", "log_scales", "quats"]):
        if c.shape[0] != n:
            raise ValueError(f"{name} has {c.shape[0]} rows; expected {n} like means")
    data = np.concatenate(cols, axis=1).astype("<f4")
    if not np.all(np.isfinite(data)):
        raise ValueError("cannot write non-finite Gaussian parameters to PLY")
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {p}\n" for p in _PROPS) + "end_header\n"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())


def read_ply(path) -> dict:
    """Read a PLY written in the layout above; returns means, log_scales, quats, opacity_logits, colors."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if end < 0:
        raise ValueError(f"{path} is not a PLY file (no end_header)")
    header = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: {_format_of(header)} PLY is not supported; only binary little-endian PLY is read "
                         "(export-ply writes it)")
    props = [line.split()[-1] for line in header if line.startswith("property")]
    n = int(next(line.split()[-1] for line in header if line.startswith("element vertex")))
    data = np.frombuffer(raw[end + len(b"end_header\n"):], dtype="<f4", count=n * len(props)).reshape(n, len(props))
    col = {p: data[:, i].astype(np.float64) for i, p in enumerate(props)}
    stack = lambda names: np.stack([col[p] for p in names], axis=1)  # noqa: E731
    return {"means": stack(["x", "y", "z"]), "log_scales": stack(["scale_0", "scale_1", "scale_2"]),
            "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]), "opacity_logits": col["opacity"],
            "colors": 0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"])}


# ----------------------------------------------------------------- sparse point clouds
# A coloured point cloud (x y z as double, red green blue as uchar), the layout of Nerfstudio's
# ``ply_file_path`` / COLMAP's points3D export: the optional sparse points of a scene folder
# (docs/dataset_format.md §4).
_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1"}


def write_points_ply(path, points, colors):
    """Write points (P, 3) and RGB colours (P, 3) in [0, 1] as a binary PLY (x y z double, rgb uchar)."""
    points = np.asarray(points, dtype=np.float64)
    colors = np.asarray(colors, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or colors.shape != points.shape:
        raise ValueError(f"points and colors must both have shape (P, 3); got {points.shape} and {colors.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(colors))):
        raise ValueError("cannot write non-finite points or colours to PLY")
    rec = np.zeros(len(points), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("r", "u1"), ("g", "u1"), ("b", "u1")])
    rec["x"], rec["y"], rec["z"] = points.T
    rgb = np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)
    rec["r"], rec["g"], rec["b"] = rgb.T
    header = ("ply\nformat binary_little_endian 1.0\n" + f"element vertex {len(points)}\n"
              + "".join(f"property double {p}\n" for p in "xyz")
              + "".join(f"property uchar {p}\n" for p in ("red", "green", "blue")) + "end_header\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())


def read_points_ply(path):
    """Read a binary little-endian PLY point cloud with x y z (float or double) and optional
    red green blue (uchar) -> (points (P, 3) float64, colors (P, 3) in [0, 1] or None)."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file (no 'ply' magic or end_header); write it with write_points_ply")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: {_format_of(header)} PLY point clouds are not supported; re-save it as binary "
                         "little-endian PLY (e.g. Open3D write_point_cloud(..., write_ascii=False), or "
                         "d2gs_np.data.ply.write_points_ply)")
    fields, n, in_vertex = [], None, False
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
            elif n is not None:
                break  # elements after the vertices are not read
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: vertex property type {parts[1]!r} is not supported (float, double, uchar)")
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [f[0] for f in fields]
    if n is None or not all(a in names for a in "xyz"):
        raise ValueError(f"{path}: needs a vertex element with x, y, z properties")
    dt = np.dtype(fields)
    body = raw[end + len(b"end_header\n"):]
    if len(body) < n * dt.itemsize:
        raise ValueError(f"{path} is truncated: {n} vertices need {n * dt.itemsize} bytes, {len(body)} present")
    rec = np.frombuffer(body, dtype=dt, count=n)
    pts = np.stack([rec[a].astype(np.float64) for a in "xyz"], axis=1)
    cols = None
    if all(c in names for c in ("red", "green", "blue")):
        cols = np.stack([rec[c].astype(np.float64) / 255.0 for c in ("red", "green", "blue")], axis=1)
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: point coordinates contain NaN or inf")
    return pts, cols
