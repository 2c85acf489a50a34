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
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    props = [line.split()[-1] for line in header if line.startswith("property")]
    n = int(next(line.split()[-1] for line in header if line.startswith("element vertex")))
    data = np.frombuffer(raw[end + len(b"end_header\n"):], dtype="<f4", count=n * len(props)).reshape(n, len(props))
    col = {p: data[:, i].astype(np.float64) for i, p in enumerate(props)}
    stack = lambda names: np.stack([col[p] for p in names], axis=1)  # noqa: E731
    return {"means": stack(["x", "y", "z"]), "log_scales": stack(["scale_0", "scale_1", "scale_2"]),
            "quats": stack(["rot_0", "rot_1", "rot_2", "rot_3"]), "opacity_logits": col["opacity"],
            "colors": 0.5 + SH_C0 * stack(["f_dc_0", "f_dc_1", "f_dc_2"])}
