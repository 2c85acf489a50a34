"""Scene builders shared by the reference-check kit and the renderer tests.

Scenes are plain dicts whose keys are the argument names of ``render_fwd`` (docs/conventions.md
§10), so a scene renders with ``render_fwd(**scene, config=cfg)``.

Discontinuities. The rendered outputs are only piecewise smooth in the inputs (docs/conventions.md
§8): a (Gaussian, pixel) evaluation switches on or off when its alpha crosses 1/255, the
compositing stops when ``T * (1 - alpha)`` crosses 1e-4, the gradient through the 0.999 clamp
switches off when ``o * exp(-sigma)`` crosses 0.999, a Gaussian is culled at the near plane,
the front-to-back order changes when two depths cross, and the Jacobian's x/z, y/z clamp has a
kink. ``threshold_margins`` reports, for each of these, the smallest *relative* distance of any
evaluation to its threshold. Two implementations that round differently can only disagree
beyond rounding where a margin is within their rounding (``safe_random_scene`` keeps it away).
"""
from __future__ import annotations

import numpy as np

from d2gs_np import constants as C

__all__ = ["extreme_scales_scene", "extreme_anisotropy_scene", "near_plane_scene", "flat_covariance_scene",
           "random_rotation", "random_scene", "cast_scene", "copy_scene", "safe_random_scene",
           "threshold_margins", "threshold_margin", "camera_scene"]


def random_rotation(rng, max_angle=np.pi):
    """A rotation matrix (3, 3) about a uniformly random axis by an angle uniform in [0, max_angle]."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = rng.uniform(0.0, max_angle)
    return _so3_exp(axis * angle)


def random_scene(
    rng,
    n,
    width,
    height,
    dtype=np.float64,
    depth_range=(2.0, 6.0),
    sigma_px_range=(1.0, 8.0),
    opacity_range=(0.05, 0.95),
    border_px=4.0,
    max_camera_angle=0.6,
):
    """A random scene of ``n`` Gaussians in front of a camera with a non-identity pose.

    Gaussians are drawn in the camera frame: pixel position (u, v) uniform over the image widened
    by ``border_px``, camera depth uniform in ``depth_range``, per-axis standard deviations such
    that the projected size is ``sigma_px_range`` pixels (a few to tens of pixels of footprint),
    random rotations and raw (non-unit) quaternions, opacities uniform in ``opacity_range``,
    colours and background uniform in [0, 1]. The means are then mapped to world coordinates with
    a random ``cam_T_world`` (rotation up to ``max_camera_angle`` rad, translation ~ N(0, 1)).

    Returns dict(means (n,3), quats (n,4) wxyz, scales (n,3) linear, opacities (n,),
    colors (n,3), cam_T_world (4,4), K (3,3), width, height, background (3,)), all float arrays
    of ``dtype``.
    """
    f = rng.uniform(0.8, 1.2) * max(width, height)
    K = np.array(
        [
            [f * rng.uniform(0.95, 1.05), 0.0, width / 2 + rng.uniform(-1.0, 1.0)],
            [0.0, f * rng.uniform(0.95, 1.05), height / 2 + rng.uniform(-1.0, 1.0)],
            [0.0, 0.0, 1.0],
        ]
    )
    R_v = random_rotation(rng, max_camera_angle)
    t_v = rng.normal(size=3)
    cam_T_world = np.eye(4)
    cam_T_world[:3, :3] = R_v
    cam_T_world[:3, 3] = t_v

    u = rng.uniform(-border_px, width + border_px, size=n)
    v = rng.uniform(-border_px, height + border_px, size=n)
    z = rng.uniform(*depth_range, size=n)
    p_c = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    means = (p_c - t_v) @ R_v  # p_w = R_v^T (p_c - t_v), row-wise

    sigma_px = rng.uniform(*sigma_px_range, size=(n, 3))
    scales = sigma_px * z[:, None] / K[0, 0]
    quats = rng.normal(size=(n, 4))
    quats *= rng.uniform(0.5, 2.0, size=(n, 1)) / np.linalg.norm(quats, axis=1, keepdims=True)
    opacities = rng.uniform(*opacity_range, size=n)
    colors = rng.uniform(0.0, 1.0, size=(n, 3))
    background = rng.uniform(0.0, 1.0, size=3)
    scene = dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        cam_T_world=cam_T_world,
        K=K,
        width=int(width),
        height=int(height),
        background=background,
    )
    return cast_scene(scene, dtype)


def cast_scene(scene, dtype):
    """A copy of ``scene`` with every float array cast to ``dtype`` (ints kept)."""
    out = {}
    for key, val in scene.items():
        out[key] = np.array(val, dtype=dtype) if isinstance(val, np.ndarray) else val
    return out


def copy_scene(scene):
    """A deep copy of the arrays of ``scene`` (so a test can perturb one entry)."""
    return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in scene.items()}


def safe_random_scene(rng, n, width, height, dtype=np.float64, margin=1e-4, config=None, max_tries=200,
                      **kwargs):
    """``random_scene`` redrawn until ``threshold_margin(scene, config) >= margin``.

    Raises RuntimeError after ``max_tries`` draws (lower the margin, n or the image size).
    """
    for _ in range(max_tries):
        scene = random_scene(rng, n, width, height, dtype=dtype, **kwargs)
        if threshold_margin(scene, config) >= margin:
            return scene
    raise RuntimeError(f"no scene with threshold margin >= {margin} in {max_tries} draws")


def threshold_margins(scene, config=None):
    """Smallest relative distance to each threshold of the renderer, as a dict of floats.

    Keys (each the min over the relevant evaluations; ``inf`` if there are none):
      "alpha_threshold": |alpha - 1/255| / (1/255) over (Gaussian, pixel) pairs evaluated before
          the pixel stopped;
      "alpha_clamp": |o*exp(-sigma) - 0.999| / 0.999 over the same pairs with alpha >= 1/255;
      "transmittance": |T*(1-alpha) - 1e-4| / 1e-4 over the same pairs with alpha >= 1/255;
      "near_plane": |z - near| / near over Gaussians in front of the camera (a Gaussian between
          the camera and the near plane is culled on either side of a small step, so only the
          distance to the plane matters);
      "depth_order": |z_i - z_j| / max(|z_i|, |z_j|) over consecutive visible Gaussians in the
          front-to-back order;
      "jacobian_clamp": |x/z - limit| / |limit| over visible Gaussians and the four x/z, y/z
          limits of the Jacobian clamp (a kink of the gradient).
    Computed from the float64 reference renderer's saved state (d2gs_np.reference).
    """
    from d2gs_np.reference import render_fwd

    scene64 = cast_scene(scene, np.float64)
    _, saved = render_fwd(**scene64, config=config)
    proj, ras = saved["proj"], saved["raster"]
    near = saved["config"].near_plane
    inf = float("inf")

    def _min(a):
        a = np.asarray(a, dtype=np.float64)
        return float(a.min()) if a.size else inf

    ev = ras["evaluated"]  # (S, H, W) pixel not stopped before this Gaussian
    alpha, raw, T = ras["alpha"], ras["raw_alpha"], ras["T"]
    passed = ev & (alpha >= C.ALPHA_THRESHOLD)
    out = {
        "alpha_threshold": _min(np.abs(alpha[ev] - C.ALPHA_THRESHOLD) / C.ALPHA_THRESHOLD),
        "alpha_clamp": _min(np.abs(raw[passed] - C.ALPHA_MAX) / C.ALPHA_MAX),
        "transmittance": _min(np.abs(T[passed] * (1.0 - alpha[passed]) - C.TRANSMITTANCE_MIN)
                              / C.TRANSMITTANCE_MIN),
    }
    z = proj["depths"]
    front = z > 0
    out["near_plane"] = _min(np.abs(z[front] - near) / near)
    zs = z[saved["order"]]
    out["depth_order"] = _min(np.abs(np.diff(zs)) / np.maximum(np.abs(zs[1:]), np.abs(zs[:-1])))
    vis = proj["radii"][:, 0] > 0
    rel = []
    for ratio, lims in ((proj["x_over_z"], proj["lim_x"]), (proj["y_over_z"], proj["lim_y"])):
        for lim in lims:
            rel.append(np.abs(ratio[vis] - lim) / abs(lim))
    out["jacobian_clamp"] = _min(np.concatenate(rel)) if rel else inf
    return out


def threshold_margin(scene, config=None):
    """min over ``threshold_margins(scene, config)``: the smallest relative distance to any threshold."""
    return min(threshold_margins(scene, config).values())


def camera_scene(p_c, sigmas, opacities, colors, width, height, f=None, quats=None, rng=None):
    """A scene from camera-frame means p_c (n,3) and world scales ``sigmas`` (n,3), identity-ish pose.

    K has focal lengths (f, 1.02 f) (default f = max(width, height)) and its principal point at
    the image centre; the pose is a random rotation up to 0.3 rad and a translation ~ N(0, 0.1).
    """
    rng = np.random.default_rng(7) if rng is None else rng
    n = len(p_c)
    f = float(max(width, height)) if f is None else f
    K = np.array([[f, 0.0, width / 2.0], [0.0, f * 1.02, height / 2.0], [0.0, 0.0, 1.0]])
    R_v = random_rotation(rng, 0.3)
    t_v = rng.normal(size=3) * 0.1
    T = np.eye(4)
    T[:3, :3] = R_v
    T[:3, 3] = t_v
    means = (np.asarray(p_c, float) - t_v) @ R_v
    if quats is None:
        quats = rng.normal(size=(n, 4))
    return dict(means=means, quats=np.asarray(quats, float), scales=np.asarray(sigmas, float),
                opacities=np.asarray(opacities, float), colors=np.asarray(colors, float),
                cam_T_world=T, K=K, width=width, height=height, background=rng.uniform(0, 1, 3))


def extreme_scales_scene():
    """24 Gaussians, 30x26: scale magnitudes log-uniform in [1e-6, 1e3] (anisotropy <= 10 each), one
    dilation-only point and one far larger than the image (seed 21)."""
    rng = np.random.default_rng(21)
    n, W, H = 24, 30, 26
    p_c = np.stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n), rng.uniform(2, 6, n)], axis=1)
    sig = 10.0 ** (rng.uniform(-6, 3, size=(n, 1)) + rng.uniform(0, 1, size=(n, 3)))
    sig[0] = [1e-6, 2e-6, 3e-6]
    sig[1] = [1e3, 2e3, 3e2]
    return camera_scene(p_c, sig, rng.uniform(0.05, 0.9, n), rng.uniform(0, 1, (n, 3)), W, H, rng=rng)


def extreme_anisotropy_scene():
    """20 Gaussians, 30x26: needles and pancakes, per-Gaussian scale ratios up to 1e9 (seed 22)."""
    rng = np.random.default_rng(22)
    n, W, H = 20, 30, 26
    p_c = np.stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.6, 0.6, n), rng.uniform(2, 6, n)], axis=1)
    sig = 10.0 ** rng.uniform(-6, 3, size=(n, 3))
    sig[0] = [1e3, 1e-6, 1e-6]
    sig[1] = [1e3, 1e3, 1e-6]
    return camera_scene(p_c, sig, rng.uniform(0.05, 0.9, n), rng.uniform(0, 1, (n, 3)), W, H, rng=rng)


def near_plane_scene():
    """6 Gaussians, 24x20, identity pose: z = 1.5 near (huge footprint), z = near exactly, below
    near, behind the camera, and two ordinary ones (seed 22). The means are the exact camera-frame
    positions, so z == near is exactly representable."""
    rng = np.random.default_rng(22)
    near = C.NEAR_PLANE
    p_c = np.array([[0.0, 0.0, near * 1.5], [0.001, 0.0, near], [0.0, 0.001, near * 0.5], [0.1, 0.1, -1.0],
                    [0.2, -0.1, 3.0], [-0.3, 0.2, 2.5]])
    sig = np.array([[1e-4, 2e-4, 1e-4], [0.1] * 3, [0.1] * 3, [0.1] * 3, [0.2, 0.1, 0.3], [0.1, 0.3, 0.2]])
    scene = camera_scene(p_c, sig, [0.3, 0.9, 0.9, 0.9, 0.7, 0.6], rng.uniform(0, 1, (6, 3)), 24, 20, rng=rng)
    scene["cam_T_world"] = np.eye(4)
    scene["means"] = p_c
    return scene


def flat_covariance_scene():
    """6 Gaussians, 20x20: singular 3D covariances, one, two or all three scales exactly 0 (seed 23)."""
    rng = np.random.default_rng(23)
    n, W, H = 6, 20, 20
    p_c = np.stack([rng.uniform(-0.4, 0.4, n), rng.uniform(-0.4, 0.4, n), rng.uniform(2, 4, n)], axis=1)
    sig = np.array([[0.3, 0.2, 0.0], [0.0, 0.0, 0.25], [0.0, 0.0, 0.0], [0.2, 1e-12, 0.3], [0.15, 0.2, 0.1],
                    [0.0, 0.3, 0.0]])
    return camera_scene(p_c, sig, rng.uniform(0.2, 0.9, n), rng.uniform(0, 1, (n, 3)), W, H, rng=rng)


def _hat(phi):
    return np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])


def _so3_exp(phi):
    """Rodrigues' formula (scene drawing only; no small-angle subtleties needed here)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = np.linalg.norm(phi)
    W = _hat(phi)
    if theta < 1e-8:
        return np.eye(3) + W + 0.5 * W @ W
    return np.eye(3) + np.sin(theta) / theta * W + (1.0 - np.cos(theta)) / theta**2 * W @ W
