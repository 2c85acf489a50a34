"""Synthetic blurry dynamic scenes with full ground truth, by analytic ray casting.

The ground truth is NOT a Gaussian scene: every image is ray cast in
vectorised NumPy against an analytic world, so a Gaussian model fitted to it
is an approximation, as with real footage.

World (world units ~ metres; y is UP, the camera looks roughly along -z):
- a closed room ``[-3, 3] x [0, 3.2] x [-2.5, 6]`` (floor, ceiling, four
  walls; every ray hits something, there is no sky at infinity), with a
  static textured box standing on the floor;
- procedural textures with structure at several scales: soft-edged checkers,
  stripes, colour gradients and smooth noise (sums of random plane waves).
  Edges are softened over ~1-2 pixels at the default resolution, so blur is
  visible and matters, but a few thousand Gaussians can fit them;
- flat Lambertian shading with one fixed directional light (view
  independent; no shadows, so nothing outside a mover changes with time);
- moving objects (``moving_objects=True``): two textured, spinning spheres on
  smooth (C-infinity) curves of normalised time t.

Camera: ``camera_pose(world, t)`` is a C-infinity function of t: an arc
around the scene centre, low-frequency sway (sums of sines, 0.5-2.5 cycles
per clip), a faster smooth shake in position and orientation (5-9 cycles per
clip), looking at a slowly swaying target with a slowly varying roll.

Frames (docs/method.md §4): mid-exposure times ``t_k = k / (N - 1)``; exposure
length in normalised time ``tau = exposure_fraction / (N - 1)``. The blurry
frame k is the mean of S sharp sub-frames at times
``t_k + (u_i - 0.5) tau`` with ``u_i = i / (S - 1)`` (evenly spaced,
endpoints included, the same spacing as the model's virtual poses, Eq. 9),
each rendered with BOTH the camera and the objects at that time, each with
``supersample x supersample`` samples per pixel (box-filter anti-aliasing).
The true exposure start / end poses are ``camera_pose(t_k -+ tau / 2)``: the
true camera moves along its curved path inside the exposure, not along the
model's geodesic. With exposure 0 the frame is rendered once (blurry == sharp).

Motion mask of frame k: pixels of which ANY sample of ANY sub-frame sees a
moving object. Estimated pose: ``exp(delta) @ T_true`` (left perturbation,
se(3) tangent (rho, phi)), with each component of phi ~ N(0, rot_noise_deg in
radians) and each component of rho ~ N(0, trans_noise_fraction *
scene_scale). Test views: sharp renders at a subset of training times from
the true camera moved by ``+-test_offset_fraction * scene_scale`` along its
own x axis (alternating sides).

Poses returned are ``cam_T_world`` (world -> camera, OpenCV axes); pixel
(i, j) has its centre at (j + 0.5, i + 0.5) (docs/conventions.md §2).
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2gs_np.base.checks import check_bool, check_int, check_number
from d2gs_np.data.camera_paths import as_times, eval_sines, fov_intrinsics, random_sines, shaken_look_at
from d2gs_np.data.raycast import cast_depth, cast_view, stratified_offsets
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.geometry.so3 import so3_exp

__all__ = [
    "SyntheticConfig",
    "PRESETS",
    "SCENE_SCALE",
    "SyntheticWorld",
    "build_world",
    "camera_pose",
    "object_states",
    "frame_times",
    "exposure_length",
    "intrinsics",
    "render_view",
    "depth_map",
    "frame_depth_map",
    "perturb_poses",
    "generate",
    "render_clip",
    "make_scene",
    "write_synthetic_scene",
]

# Rough scene extent (world units): the camera's distance to the scene centre.
# Pose noise and test-view offsets are fractions of it.
SCENE_SCALE = 4.0


# ============================================================================ config
@dataclass(frozen=True)
class SyntheticConfig:
    """Generator settings. Validated on construction (ValueError / TypeError)."""

    width: int = 240  # image width in pixels
    height: int = 135  # image height in pixels
    num_frames: int = 24  # N training frames, t_k = k / (N - 1)
    exposure_fraction: float = 0.7  # exposure / frame interval, in [0, 1]; 0 = sharp video
    subframes: int = 16  # S sharp sub-frames averaged per blurry frame (>= 2 if exposure > 0)
    supersample: int = 2  # samples per pixel per axis (2 -> 2x2 anti-aliasing)
    moving_objects: bool = True  # two moving spheres on/off
    shake_scale: float = 1.0  # multiplies the amplitudes of the fast hand shake (position and rotation)
    shake_freq_scale: float = 1.0  # multiplies the frequencies of the fast hand shake (cycles per clip)
    # Pose noise (std of each rotation / translation component): 0.25 deg ~ 0.9 px and
    # 0.0025 * 4 = 1 cm ~ 0.4 px at the back wall, against 2-5 px of blur per frame.
    rot_noise_deg: float = 0.25  # degrees
    trans_noise_fraction: float = 0.0025  # fraction of SCENE_SCALE
    num_test_views: int = 4  # sharp views from a sideways-offset camera
    test_offset_fraction: float = 0.15  # test camera offset along its x axis / SCENE_SCALE
    fov_x_deg: float = 60.0  # horizontal field of view (square pixels, centred principal point)
    seed: int = 0  # seeds textures, paths' phases, pose noise

    def __post_init__(self):
        check_int(self.width, "SyntheticConfig.width", 1)
        check_int(self.height, "SyntheticConfig.height", 1)
        check_int(self.num_frames, "SyntheticConfig.num_frames", 2, hint="times are k / (N - 1)")
        check_int(self.subframes, "SyntheticConfig.subframes", 1)
        check_int(self.supersample, "SyntheticConfig.supersample", 1)
        check_int(self.num_test_views, "SyntheticConfig.num_test_views", 0, self.num_frames, hint="at most num_frames")
        check_int(self.seed, "SyntheticConfig.seed", 0)
        check_bool(self.moving_objects, "SyntheticConfig.moving_objects")
        check_number(self.exposure_fraction, "SyntheticConfig.exposure_fraction", 0.0, 1.0)
        if self.exposure_fraction > 0 and self.subframes < 2:
            raise ValueError(
                f"SyntheticConfig.subframes must be >= 2 when exposure_fraction > 0 (got subframes="
                f"{self.subframes}, exposure_fraction={self.exposure_fraction}); use >= 16 for smooth blur, "
                "or set exposure_fraction=0 for a sharp video"
            )
        check_number(self.shake_scale, "SyntheticConfig.shake_scale", 0.0)
        check_number(self.shake_freq_scale, "SyntheticConfig.shake_freq_scale", 0.0, lo_open=True)
        for name in ("rot_noise_deg", "trans_noise_fraction", "test_offset_fraction"):
            check_number(getattr(self, name), f"SyntheticConfig.{name}", 0.0)
        check_number(self.fov_x_deg, "SyntheticConfig.fov_x_deg", 10.0, 120.0, hint="degrees")


PRESETS = {
    # no moving objects; blurry; noisy poses
    "static": SyntheticConfig(moving_objects=False, shake_scale=8.0, shake_freq_scale=0.25),
    # moving objects; exposure 0 (rendered once per frame); true poses given as the estimates
    "sharp": SyntheticConfig(exposure_fraction=0.0, subframes=1, rot_noise_deg=0.0, trans_noise_fraction=0.0),
    # moving objects; blurry: exposure 0.7 of the frame interval and a slow, wide hand shake (8x the
    # base amplitudes at 1/4 of the base frequencies), so the inputs are clearly degraded while the
    # path inside one exposure stays close to the model's geodesic (the base shake curves so much
    # within an exposure that no geodesic blur model could deblur it; examples/blur_ceiling.py,
    # docs/results.md §14). Noisy poses.
    "dynamic": SyntheticConfig(shake_scale=8.0, shake_freq_scale=0.25),
}


def preset_overrides(cls, presets, preset, seed, overrides, what="preset"):
    """(base config, overrides) of a preset name or a ``cls`` instance, with ``seed`` folded into the
    overrides; unknown names and override fields are errors that list the valid ones."""
    if isinstance(preset, cls):
        base = preset
    elif preset in presets:
        base = presets[preset]
    else:
        raise ValueError(f"unknown {what} {preset!r}; choose one of {sorted(presets)} or pass a {cls.__name__}")
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise TypeError(f"unknown {cls.__name__} override(s) {unknown}; valid fields: {sorted(fields)}")
    if seed is not None:
        overrides = dict(overrides, seed=seed)
    return base, overrides


def _resolve_config(preset, seed, overrides):
    base, overrides = preset_overrides(SyntheticConfig, PRESETS, preset, seed, overrides)
    return dataclasses.replace(base, **overrides)


# ============================================================================= world
# Room and static box bounds (world units, y up).
_ROOM_LO = np.array([-3.0, 0.0, -2.5])
_ROOM_HI = np.array([3.0, 3.2, 6.0])
_BOX_LO = np.array([0.9, 0.0, -1.6])
_BOX_HI = np.array([1.7, 0.8, -0.8])
_LIGHT = np.array([0.35, 0.85, 0.45]) / np.linalg.norm([0.35, 0.85, 0.45])
_AMBIENT = 0.45  # shade = ambient + (1 - ambient) * max(0, n . light)
_SCENE_CENTER = np.array([0.0, 0.9, -1.0])  # the camera looks at (a sway around) this point
# Surface ids: room faces 0..5 = 2 * axis + (1 if the face is at the upper bound), box faces 6..11
# likewise, spheres 12, 13.
_N_ROOM, _BOX0, _SPHERE0 = 6, 6, 12


@dataclass(frozen=True, eq=False)
class SyntheticWorld:
    """Everything seeded that defines the analytic world and the true motions.

    Sum-of-sines blocks are arrays (n_terms, 3, 3) of rows (amplitude, cycles per clip, phase)
    per axis: value(t) = sum_n a sin(2 pi f t + p). Build it with ``build_world(config)``.
    """

    moving_objects: bool
    noise_waves: dict  # texture name -> (n, 4) rows (kx, ky [cycles / unit], phase [cycles], amplitude)
    colors: dict  # texture name -> (m, 3) palette
    cam_arc: tuple  # (radius, theta_mid, theta_span, height)
    cam_sway: np.ndarray  # eye position sway, sum-of-sines (n, 3 [a f p], 3 axes)
    cam_shake: np.ndarray  # eye position shake
    target_sway: np.ndarray  # look-at target sway
    rot_shake: np.ndarray  # camera-frame rotation vector (shake + slow roll)
    sphere_radius: np.ndarray  # (2,)
    sphere_params: np.ndarray  # (2, 8) path phases / amplitudes (see object_states)


def build_world(config: SyntheticConfig) -> SyntheticWorld:
    """The seeded analytic world of ``config`` (depends on seed, moving_objects and the shake scales)."""
    if not isinstance(config, SyntheticConfig):
        raise TypeError(f"config must be a SyntheticConfig; got {type(config).__name__}")
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 1]))

    def waves(n, lam_lo, lam_hi):
        lam = rng.uniform(lam_lo, lam_hi, n)
        ang = rng.uniform(0.0, np.pi, n)
        k = 1.0 / lam  # cycles per world unit
        return np.stack([k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 1, n), np.full(n, 1.1 / np.sqrt(n))], 1)

    def jitter(c, amount=0.06):
        return np.clip(np.asarray(c, dtype=np.float64) + rng.uniform(-amount, amount, np.shape(c)), 0.0, 1.0)

    noise_waves = {
        "floor": waves(4, 1.0, 3.0),
        "back": waves(4, 0.8, 2.5),
        "right": waves(4, 0.6, 2.0),
        "plain": waves(3, 1.5, 4.0),
        "box": waves(3, 0.5, 1.5),
    }
    colors = {
        "floor": jitter([[0.86, 0.78, 0.62], [0.36, 0.23, 0.16]]),
        "back": jitter([[0.18, 0.32, 0.62], [0.22, 0.62, 0.55], [0.93, 0.92, 0.85], [0.95, 0.55, 0.15],
                        [0.95, 0.95, 0.9], [0.1, 0.1, 0.12]]),
        "left": jitter([[0.25, 0.55, 0.25], [0.92, 0.93, 0.86], [0.55, 0.75, 0.45]]),
        "right": jitter([[0.7, 0.2, 0.25], [0.95, 0.7, 0.72], [0.45, 0.1, 0.15]]),
        "plain": jitter([[0.78, 0.78, 0.76], [0.6, 0.6, 0.62]]),
        "box": jitter([[0.95, 0.8, 0.2], [0.45, 0.2, 0.6]]),
        "sphere0": jitter([[0.9, 0.15, 0.1], [0.97, 0.95, 0.9]]),
        "sphere1": jitter([[0.15, 0.3, 0.9], [0.98, 0.85, 0.2]]),
    }
    cam_arc = (4.3, rng.uniform(-0.05, 0.05), 0.4, 1.55)
    cam_sway = random_sines(rng, [[0.06, 0.05, 0.06], [0.03, 0.03, 0.03]], [0.8, 1.7])
    cam_shake = random_sines(rng, [[0.006, 0.006, 0.004], [0.004, 0.004, 0.003]], [5.5, 8.5])
    target_sway = random_sines(rng, [[0.12, 0.06, 0.0]], [0.9])
    # camera-frame rotation vector (x: tilt, y: pan, z: roll): a fast shake of ~0.5 deg plus a slow roll
    rot_shake = np.concatenate([
        random_sines(rng, [[0.009, 0.009, 0.005], [0.006, 0.006, 0.004]], [6.0, 9.0]),
        random_sines(rng, [[0.0, 0.0, 0.03]], [0.6]),
    ])
    # Stronger hand shake scales only the amplitudes (row 0 of each (a, f, p) block): the path
    # keeps its shape and smoothness, the phases and frequencies are the same draws.
    cam_shake[:, 0, :] *= config.shake_scale
    rot_shake[:2, 0, :] *= config.shake_scale
    # A slower shake (row 1: cycles per clip) bends the path less inside one exposure, so the
    # model's geodesic between the exposure endpoints (docs/method.md §4, Eq. 9) fits it better.
    cam_shake[:, 1, :] *= config.shake_freq_scale
    rot_shake[:2, 1, :] *= config.shake_freq_scale
    sphere_radius = np.array([0.35, 0.25])
    sphere_params = rng.uniform(-0.3, 0.3, (2, 8))
    return SyntheticWorld(
        moving_objects=config.moving_objects, noise_waves=noise_waves, colors=colors, cam_arc=cam_arc,
        cam_sway=cam_sway, cam_shake=cam_shake, target_sway=target_sway, rot_shake=rot_shake,
        sphere_radius=sphere_radius, sphere_params=sphere_params,
    )


def camera_pose(world: SyntheticWorld, t):
    """True camera ``cam_T_world`` at time(s) t: scalar -> (4, 4), (M,) -> (M, 4, 4).

    C-infinity in t (sums of sines, an arc, look-at, a rotation exponential), defined for all
    real t (exposures of the first and last frames reach slightly outside [0, 1]).
    """
    t = as_times(t)
    tt = np.atleast_1d(t)
    radius, theta_mid, theta_span, height = world.cam_arc
    theta = theta_mid + theta_span * (tt - 0.5)
    eye = np.stack([
        _SCENE_CENTER[0] + radius * np.sin(theta),
        np.full_like(tt, height),
        _SCENE_CENTER[2] + radius * np.cos(theta),
    ], axis=1)
    eye = eye + eval_sines(world.cam_sway, tt) + eval_sines(world.cam_shake, tt)
    target = _SCENE_CENTER + eval_sines(world.target_sway, tt)
    poses = shaken_look_at(eye, target, eval_sines(world.rot_shake, tt))  # shake: about the camera centre
    return poses[0] if t.ndim == 0 else poses


def object_states(world: SyntheticWorld, t):
    """Moving spheres at time t (scalar): (centres (n, 3), rotations (n, 3, 3), radii (n,)).

    n = 0 when the world has no moving objects. Sphere 0 travels left to right in hops with a
    rolling spin; sphere 1 circles above the floor, spinning about a tilted axis. All smooth in t.
    """
    t = float(t)
    if not world.moving_objects:
        return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0)
    a, b = world.sphere_params
    c0 = np.array([
        -1.5 + 2.6 * t + 0.15 * np.sin(2 * np.pi * t + a[0]),
        0.4 + 0.35 * np.sin(np.pi * 1.5 * t + a[1]) ** 2,
        -0.15 + 0.3 * np.sin(np.pi * t + a[2]),
    ])
    ang1 = 2 * np.pi * t + b[0]
    c1 = np.array([-0.5 + 0.55 * np.cos(ang1), 1.55 + 0.35 * np.sin(ang1), -1.3 + 0.25 * np.sin(ang1 + b[1])])
    axis1 = np.array([0.3, 1.0, 0.2 + b[2]])
    R0 = so3_exp(np.array([0.0, 0.0, -(4.0 + a[3]) * t]))
    R1 = so3_exp((5.0 + b[3]) * t * axis1 / np.linalg.norm(axis1))
    return np.stack([c0, c1]), np.stack([R0, R1]), world.sphere_radius.copy()


# ========================================================================= textures
# Textures use a C1 periodic wave instead of np.sin: float64 np.sin is slow per element, and textures
# are evaluated for every sample of every sub-frame.
def _wave(x):
    """C1 periodic wave of period 1 in [-1, 1], a close stand-in for sin(2 pi x) (max gap 0.02).

    A triangle wave y(x) (zeros at x = 0, 1/2, peaks at 1/4, 3/4) passed through the cubic
    1.5 y - 0.5 y^3, whose slope vanishes at y = +-1, so the result has a continuous derivative.
    """
    y = x - 0.25
    y -= np.floor(y)  # in [0, 1)
    y -= 0.5
    np.abs(y, out=y)
    y *= -4.0
    y += 1.0  # triangle: +1 at x = 1/4, -1 at x = 3/4
    return y * (1.5 - 0.5 * y * y)


def _soft(x, softness):
    """Smooth step of x (around 0) to [0, 1]; transition half-width ~ softness."""
    return 0.5 + 0.5 * np.tanh(x / softness)


def _checker(u, v, period, softness=0.25):
    """Soft checker with squares of side ``period`` (world units)."""
    return _soft(_wave(u / (2.0 * period)) * _wave(v / (2.0 * period)), softness)


def _stripes(u, v, period, angle, softness=0.3):
    return _soft(_wave((u * np.cos(angle) + v * np.sin(angle)) / period), softness)


def _noise(u, v, waves):
    """Smooth noise in ~[0, 1] from random plane waves (rows kx, ky, phase, amplitude; k in cycles/unit)."""
    s = np.zeros_like(u)
    for kx, ky, ph, amp in waves:
        s += amp * _wave(kx * u + ky * v + ph)
    return 0.5 + 0.5 * np.tanh(s)


def _smoothstep(x, half_width):
    """C1 cubic step from 0 (x <= -half_width) to 1 (x >= half_width): exactly 0 / 1 outside."""
    s = np.clip(0.5 + 0.5 * x / half_width, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _band(x, lo, hi, half_width):
    """1 inside [lo, hi], 0 outside [lo - half_width, hi + half_width], C1 in between."""
    return _smoothstep(x - lo, half_width) * _smoothstep(hi - x, half_width)


def _mix(c0, c1, w):
    """Channel-first colour blend: c0, c1 colours (3,) or fields (3, M); w (M,) -> (3, M)."""
    c0 = np.asarray(c0, dtype=np.float64)
    c1 = np.asarray(c1, dtype=np.float64)
    c0 = c0[:, None] if c0.ndim == 1 else c0
    c1 = c1[:, None] if c1.ndim == 1 else c1
    return c0 + (c1 - c0) * w


def _texture(world, surf, x, y, z, normal, states):
    """Albedo (3, M), channel first, of surface ``surf`` at world points (x, y, z), each (M,)."""
    C, W = world.colors, world.noise_waves
    if surf == 2:  # floor (y = lo)
        c = _mix(C["floor"][0], C["floor"][1], _checker(x, z, 0.5))
        return c * (0.8 + 0.3 * _noise(x, z, W["floor"]))
    if surf == 4:  # back wall (z = lo)
        c = _mix(C["back"][0], C["back"][1], np.clip((x + 3.0) / 6.0, 0.0, 1.0))
        c = _mix(c, C["back"][3], _soft(_noise(x, y, W["back"]) - 0.72, 0.04))
        # stripes and a checker poster only where their compact bands are non-zero (cost)
        i = np.flatnonzero(np.abs(y - 2.05) < 0.45 + 0.05)
        band = _band(y[i], 1.6, 2.5, 0.05)
        c[:, i] = _mix(c[:, i], C["back"][2], 0.75 * _stripes(x[i], y[i], 0.35, np.pi / 3) * band)
        i = np.flatnonzero((np.abs(x + 1.6) < 0.6 + 0.04) & (np.abs(y - 0.85) < 0.5 + 0.04))
        poster = _band(x[i], -2.2, -1.0, 0.04) * _band(y[i], 0.35, 1.35, 0.04)
        checker = _mix(C["back"][4], C["back"][5], _checker(x[i] + 2.2, y[i] - 0.35, 0.2))
        c[:, i] = _mix(c[:, i], checker, poster)
        return c
    if surf == 0:  # left wall (x = lo)
        c = _mix(C["left"][0], C["left"][1], _stripes(z, y, 0.4, 0.0, 0.35))
        return _mix(c, C["left"][2], np.clip(y / 3.2, 0.0, 1.0) * 0.6)
    if surf == 1:  # right wall (x = hi)
        c = _mix(C["right"][0], C["right"][1], _noise(z, y, W["right"]))
        return _mix(c, C["right"][2], 0.5 * _checker(z, y, 0.3))
    if surf in (3, 5):  # ceiling, front wall (behind the camera)
        return _mix(C["plain"][0], C["plain"][1], _noise(x, z if surf == 3 else y, W["plain"]))
    if _BOX0 <= surf < _SPHERE0:  # static box: checker on the two in-face coordinates
        axis = (surf - _BOX0) // 2
        u, v = [c for a, c in enumerate((x, y, z)) if a != axis]
        c = _mix(C["box"][0], C["box"][1], _checker(u + 0.05, v + 0.05, 0.2))
        return c * (0.85 + 0.25 * _noise(u, v, W["box"]))
    # moving spheres: longitude/latitude soft checker (0) or stripes (1), in the rotating frame
    k = surf - _SPHERE0
    centers, rots, radii = states
    local = normal @ rots[k]  # n in the sphere's own frame: R^T n, row-wise
    lon = np.arctan2(local[:, 2], local[:, 0]) / (2.0 * np.pi)  # in cycles
    lat = np.arcsin(np.clip(local[:, 1], -1.0, 1.0)) / (2.0 * np.pi)
    col = C[f"sphere{k}"]
    if k == 0:
        w = _soft(_wave(4.0 * lon) * _wave(4.0 * lat), 0.25)
    else:
        w = np.clip(_soft(_wave(5.0 * lat), 0.3) + 0.6 * _soft(_wave(3.0 * lon), 0.3) - 0.3, 0.0, 1.0)
    return _mix(col[0], col[1], w)


# ======================================================================== ray casting
def _cast(world, origin, dirs, t, states=None):
    """Cast rays origin (3,) + s * d for d in dirs = (dx, dy, dz), each (R,), at time t.

    Returns (rgb (3, R) channel first, ray parameter s of the first hit (R,), hit-a-mover (R,) bool).
    With d = R^T (x, y, 1) (camera z component 1) the ray parameter is the camera depth.
    Structure of arrays and no BLAS: (R, 3) @ (3, 3) products were the bottleneck.
    """
    if states is None:
        states = object_states(world, t)
    dx, dy, dz = dirs
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = [1.0 / dx, 1.0 / dy, 1.0 / dz]
        # room: exit through the nearest wall (the origin is inside)
        t_exit = [(np.where(d > 0, hi, lo) - o) * iv for d, iv, lo, hi, o in zip(dirs, inv, _ROOM_LO, _ROOM_HI, origin)]
        depth = np.minimum(np.minimum(t_exit[0], t_exit[1]), t_exit[2])
        surf = np.where(t_exit[0] == depth, 0 + (dx > 0), np.where(t_exit[1] == depth, 2 + (dy > 0), 4 + (dz > 0)))
        # static box: slab test
        tmin, tmax = [], []
        for iv, lo, hi, o in zip(inv, _BOX_LO, _BOX_HI, origin):
            t1, t2 = (lo - o) * iv, (hi - o) * iv
            tmin.append(np.minimum(t1, t2))
            tmax.append(np.maximum(t1, t2))
        t_near = np.maximum(np.maximum(tmin[0], tmin[1]), tmin[2])
        t_far = np.minimum(np.minimum(tmax[0], tmax[1]), tmax[2])
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < depth)
        if np.any(hit):
            box_surf = np.where(tmin[0] == t_near, _BOX0 + (dx < 0),
                                np.where(tmin[1] == t_near, _BOX0 + 2 + (dy < 0), _BOX0 + 4 + (dz < 0)))
            depth = np.where(hit, t_near, depth)
            surf = np.where(hit, box_surf, surf)
    # spheres (camera always outside them): nearest root of |o + s d - c|^2 = r^2
    centers, _, radii = states
    aa = dx * dx + dy * dy + dz * dz
    for k in range(len(radii)):
        oc = origin - centers[k]
        b = dx * oc[0] + dy * oc[1] + dz * oc[2]
        disc = b * b - aa * (oc @ oc - radii[k] ** 2)
        hit = disc >= 0
        if not np.any(hit):
            continue
        s = (-b - np.sqrt(np.maximum(disc, 0.0))) / aa
        hit &= (s > 0) & (s < depth)
        depth = np.where(hit, s, depth)
        surf = np.where(hit, _SPHERE0 + k, surf)
    rgb = np.empty((3, len(depth)))  # channel first: blends broadcast along the contiguous axis
    present = np.flatnonzero(np.bincount(surf, minlength=_SPHERE0 + 2))
    for sid in present:
        sel = np.flatnonzero(surf == sid)
        ds = depth[sel]
        x, y, z = (o + ds * d[sel] for o, d in zip(origin, dirs))
        if sid < _SPHERE0:
            n = np.zeros(3)
            if sid < _N_ROOM:
                n[sid // 2] = 1.0 if sid % 2 == 0 else -1.0  # inward room normal
            else:
                n[(sid - _BOX0) // 2] = 1.0 if (sid - _BOX0) % 2 == 1 else -1.0  # outward box normal
            normal = None
            shade = _AMBIENT + (1.0 - _AMBIENT) * max(float(n @ _LIGHT), 0.0)
        else:
            k = sid - _SPHERE0
            normal = np.stack([x - centers[k, 0], y - centers[k, 1], z - centers[k, 2]], axis=1) / radii[k]
            shade = _AMBIENT + (1.0 - _AMBIENT) * np.maximum(normal @ _LIGHT, 0.0)
        rgb[:, sel] = _texture(world, int(sid), x, y, z, normal, states) * shade
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return rgb, depth, surf >= _SPHERE0


def render_view(world: SyntheticWorld, cam_T_world, t, K, width, height, supersample=2):
    """Sharp ray-cast image at pose ``cam_T_world`` (4, 4) and time t (objects at t): rgb (H, W, 3)
    float64 in [0, 1] and dynamic (H, W) bool, ``supersample^2`` rays per pixel (``raycast.cast_view``)."""
    return cast_view(lambda origin, dirs: _cast(world, origin, dirs, float(t)), cam_T_world, K, width, height,
                     supersample)


def depth_map(world: SyntheticWorld, cam_T_world, t, K, width, height):
    """True depth (camera z, (H, W) float64) of the first surface hit through each pixel centre at time t."""
    return cast_depth(lambda origin, dirs: _cast(world, origin, dirs, float(t)), cam_T_world, K, width, height)


# ============================================================================ frames
def frame_times(config: SyntheticConfig):
    """Mid-exposure times t_k = k / (N - 1), (N,)."""
    return np.arange(config.num_frames) / (config.num_frames - 1)


def exposure_length(config: SyntheticConfig):
    """Exposure length tau in normalised time: exposure_fraction / (N - 1)."""
    return config.exposure_fraction / (config.num_frames - 1)


def intrinsics(config: SyntheticConfig):
    """(3, 3) K: square pixels, horizontal fov ``fov_x_deg``, principal point at the image centre."""
    return fov_intrinsics(config.width, config.height, config.fov_x_deg)


def frame_depth_map(config: SyntheticConfig, k, world=None):
    """True depth map (H, W) of training frame k: true mid-exposure pose, time t_k, pixel centres."""
    if not 0 <= k < config.num_frames:
        raise ValueError(f"frame index k must be in [0, {config.num_frames}); got {k}")
    world = build_world(config) if world is None else world
    t = frame_times(config)[k]
    return depth_map(world, camera_pose(world, t), t, intrinsics(config), config.width, config.height)


def perturb_poses(poses, rot_std_deg, trans_std, rng):
    """Left-perturbed poses exp(delta) @ T with delta = (rho, phi) ~ N(0, diag(trans_std^2 I, rot_std^2 I)).

    poses (M, 4, 4); rot_std_deg in degrees (per component of phi), trans_std in world units (per
    component of rho). Returns (perturbed (M, 4, 4), delta (M, 6)). Zero stds return exact copies.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f"poses must have shape (M, 4, 4); got {poses.shape}")
    if rot_std_deg < 0 or trans_std < 0:
        raise ValueError(f"noise stds must be >= 0; got rot_std_deg={rot_std_deg}, trans_std={trans_std}")
    M = poses.shape[0]
    delta = np.concatenate([
        rng.normal(0.0, 1.0, (M, 3)) * trans_std,
        rng.normal(0.0, 1.0, (M, 3)) * np.deg2rad(rot_std_deg),
    ], axis=1)
    if rot_std_deg == 0 and trans_std == 0:
        return poses.copy(), delta
    return se3_exp(delta) @ poses, delta


def _test_pose(T, offset):
    """The camera T moved by ``offset`` (world units) along its own x axis."""
    out = T.copy()
    out[0, 3] -= offset  # p_cam' = R (p - c - offset x_axis) = p_cam - offset e_x
    return out


def generate(config: SyntheticConfig) -> Scene:
    """Render the scene described by ``config`` (see the module docstring). In memory, float64 images."""
    if not isinstance(config, SyntheticConfig):
        raise TypeError(f"config must be a SyntheticConfig; got {type(config).__name__}")
    world = build_world(config)
    times = frame_times(config)
    gt = camera_pose(world, times)
    noise_rng = np.random.default_rng(np.random.SeedSequence([config.seed, 2]))
    est, _ = perturb_poses(gt, config.rot_noise_deg, config.trans_noise_fraction * SCENE_SCALE, noise_rng)
    scene = render_clip(
        lambda t: camera_pose(world, t), lambda T, t, K, W, H, ss: render_view(world, T, t, K, W, H, ss),
        times=times, tau=exposure_length(config), subframes=config.subframes, est_poses=est,
        K=intrinsics(config), width=config.width, height=config.height, supersample=config.supersample,
        num_test_views=config.num_test_views, test_offset=config.test_offset_fraction * SCENE_SCALE,
        exposure_fraction=config.exposure_fraction, scene_scale=SCENE_SCALE,
        depth_fn=lambda T, t, K, W, H: depth_map(world, T, t, K, W, H))
    if config.rot_noise_deg == 0 and config.trans_noise_fraction == 0:
        scene.poses_trusted = True  # the given poses are the true ones (docs/dataset_format.md §4)
    return scene


def render_clip(camera_pose_fn, render_fn, *, times, tau, subframes, est_poses, K, width, height, supersample,
                num_test_views, test_offset, exposure_fraction, scene_scale, blur_supersample=None,
                stratify=False, depth_fn=None) -> Scene:
    """Frames of a video of an analytic world, shared by every synthetic scene family.

    camera_pose_fn(t (M,)) -> true cam_T_world (M, 4, 4); render_fn(cam_T_world, t, K, W, H,
    supersample[, offset]) -> (sharp rgb (H, W, 3), moving (H, W) bool). Blurry frame k is the mean
    of ``subframes`` sharp sub-frames at t_k + (u_i - 0.5) tau, u_i evenly spaced in [0, 1], with the
    camera and the objects at that time; its mask is the union of the sub-frames' moving pixels.
    Sharp frames and test views use ``supersample`` rays per pixel side, the sub-frames
    ``blur_supersample`` (default: the same); with ``stratify`` each sub-frame's rays are shifted
    within their cells (``raycast.stratified_offsets``, passed as render_fn's ``offset``), so the
    sub-frames together sample the pixel area as finely as the exposure's time. depth_fn(cam_T_world,
    t, K, W, H) -> (H, W), if given, is each frame's and test view's true depth (``Frame.depth``).
    est_poses (N, 4, 4) are the poses the method is given. Test views: sharp renders at
    ``num_test_views`` evenly spaced training times from the true camera moved by +-test_offset
    along its own x axis (alternating sides).
    """
    W, H, ss = width, height, supersample
    ss_blur = supersample if blur_supersample is None else blur_supersample
    blurred = tau > 0
    S = subframes if blurred else 1
    u = np.linspace(0.0, 1.0, S) if S > 1 else np.array([0.5])
    offsets = stratified_offsets(S) if stratify else None
    gt = camera_pose_fn(times)
    start = camera_pose_fn(times - 0.5 * tau)
    end = camera_pose_fn(times + 0.5 * tau)

    frames = []
    for k, tk in enumerate(times):
        sharp, mask = render_fn(gt[k], tk, K, W, H, ss)
        if blurred:
            acc = np.zeros((H, W, 3))
            mask = np.zeros((H, W), dtype=bool)
            ts = tk + (u - 0.5) * tau
            sub_poses = camera_pose_fn(ts)
            for i in range(S):
                extra = (offsets[i],) if stratify else ()
                img, dyn = render_fn(sub_poses[i], ts[i], K, W, H, ss_blur, *extra)
                acc += img
                mask |= dyn
            blurry = acc / S
        else:
            blurry = sharp.copy()
        name = f"{k:04d}.png"
        frames.append(Frame(
            file_path=f"images/{name}", time=float(tk), cam_T_world=est_poses[k], K=K.copy(), width=W, height=H,
            image=blurry, mask=mask, mask_path=f"masks/{name}", sharp=sharp, sharp_file_path=f"sharp/{name}",
            gt_cam_T_world=gt[k], gt_exposure_start=start[k], gt_exposure_end=end[k],
            depth=None if depth_fn is None else depth_fn(gt[k], tk, K, W, H),
        ))

    test_frames = []
    if num_test_views > 0:
        idx = np.unique(np.round(np.linspace(0, len(times) - 1, num_test_views)).astype(int))
        for j, k in enumerate(idx):
            sign = 1.0 if j % 2 == 0 else -1.0
            T = _test_pose(gt[k], sign * test_offset)
            img, moving = render_fn(T, times[k], K, W, H, ss)
            test_frames.append(Frame(
                file_path=f"test/{j:04d}.png", time=float(times[k]), cam_T_world=T, K=K.copy(), width=W,
                height=H, image=img, gt_cam_T_world=T.copy(),
                # the view's moving pixels: novel views are scored on them apart (evaluation.runs)
                mask=np.asarray(moving, dtype=bool), mask_path=f"test/masks/{j:04d}.png",
                depth=None if depth_fn is None else depth_fn(T, times[k], K, W, H),
            ))
    return Scene(
        frames=frames, test_frames=test_frames, exposure_fraction=float(exposure_fraction),
        scene_scale=float(scene_scale), blur_subframes=int(S),
    )


def make_scene(preset="dynamic", seed=0, **overrides) -> Scene:
    """In-memory synthetic scene: ``PRESETS[preset]`` with ``seed`` and field ``overrides``.

    preset: "static", "sharp", "dynamic" (default) or a SyntheticConfig. Deterministic for a seed.
    """
    return generate(_resolve_config(preset, seed, overrides))


def write_synthetic_scene(out_dir, preset="dynamic", seed=0, overwrite=False, **overrides) -> Path:
    """Generate and write a scene folder (docs/dataset_format.md) with ``d2gs_np.data.io.write_scene``.

    Also writes ``synthetic_config.json`` (the generator settings, for provenance; loaders
    ignore it). Returns the folder path.
    """
    from d2gs_np.data.io import write_scene  # data.io imports cv2; keep it out of make_scene's path

    config = _resolve_config(preset, seed, overrides)
    scene = generate(config)
    out = Path(out_dir)
    write_scene(scene, out, overwrite=overwrite)
    with open(out / "synthetic_config.json", "w", encoding="utf-8") as fh:
        json.dump(dataclasses.asdict(config), fh, indent=2)
        fh.write("\n")
    return out
