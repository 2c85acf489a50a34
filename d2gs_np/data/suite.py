"""The scene suite: independent synthetic worlds that look like real input.

Every quality figure of the project is measured on all of these at once
(``examples/suite.py``), never on one scene. The worlds are described by what
a hand-held video of a real place looks like, not by what our method fits:
presets are never tuned until a method passes.

What is in a world
- Flat textured patches (rectangles and disks) ray cast exactly in NumPy, so
  the truth is not a Gaussian scene. Textures are real photographs shipped
  with scikit-image (``skimage.data``): brick, gravel and grass (Brodatz-like
  texture photographs), the astronaut (NASA, public domain), Chelsea the cat
  and the coffee cup (Stefan van der Walt and Rachel Michelle Walt, CC0), the
  rocket (SpaceX, CC0), the Hubble eXtreme Deep Field (NASA, public domain)
  and the coins (Greek coins from Pompeii, Brooklyn Museum, no known
  copyright). Each texture is area-resampled once so that one texel is half
  a pixel at the patch's reference viewing distance: detail at pixel scale,
  as a real photograph has it, with no aliasing from minification. Grey
  photographs are tinted.
- Flat shading by one directional light (two-sided; a moving patch's shade
  changes as it turns, as a real object's would).
- Moving rigid objects (``Mover``): a tumbling cube, a swinging sign on a
  hinge, a disk rolling on the floor, a card that enters and leaves the frame,
  a large panel that covers about a quarter of the frame and sways.

Camera: a look-at path with a pan (``pan``: world units of sideways travel
over the clip; ``yaw_deg``: how far the view turns about the vertical over the
clip), a low-frequency sway and a hand shake in position and orientation
(``shake`` scales the amplitudes; ``shake_cycles`` is the shake's frequency
in cycles per clip), all C-infinity in t. Blur is what the camera's turn and
shake make of pixel-scale photographic detail within one exposure.

Frames follow ``synthetic.render_clip``: t_k = k / (N - 1), exposure length
tau = exposure_fraction / (N - 1), blurry frames averaged over sub-frames with
camera and objects moving, masks the union of moving pixels, test views from a
sideways-offset camera.

Pose error (the poses the method is given): est_k = exp(delta_k) @ T_k with
delta_k = (rho, phi) the sum of an i.i.d. part and a drifting part (a
normalised Gaussian random walk over the frames; ``drift`` is the share of
the error variance that drifts). ``rot_noise_deg`` is the RMS rotation angle
|phi| over frames, ``trans_noise`` the RMS translation error |rho| as a
fraction of the scene depth (the camera's distance to the back wall).

Depth prior (``depth_prior``): each training frame also gets what a depth network would give
for it, modelled, not run: the true depth with its edges blurred (a Gaussian of
``prior_edge_px`` on the disparity; networks smooth depth boundaries, and blur widens them),
times a smooth relative error (exp of ``prior_rel_error`` times a unit-variance random field
smooth over an eighth of the width, drawn anew for each frame; ``prior_shared_error`` of its
variance instead one field for every frame, a network's bias that repeats frame to frame and
that no fusion over the frames removes). "video": a depth up to one
unknown scale for the clip, as video depth models give it (Align3R, which the paper uses);
"monocular": a disparity up to an unknown scale and shift per frame, as single-image networks
give it. Drawn from its own random stream: the images, poses and masks are those of the scene
without it.
"""
from __future__ import annotations

import dataclasses
import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2gs_np.base.checks import check_bool, check_choice, check_int, check_number
from d2gs_np.data.camera_paths import as_times, eval_sines, fov_intrinsics, random_sines, shaken_look_at
from d2gs_np.data.raycast import cast_depth, cast_view
from d2gs_np.data.scene import Scene
from d2gs_np.data.synthetic import preset_overrides, render_clip
from d2gs_np.geometry.camera import project_points
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.geometry.so3 import so3_exp

__all__ = ["SuiteConfig", "SUITE", "Mover", "SuiteWorld", "build_suite_world", "suite_camera_pose",
           "render_suite_view", "suite_depth_map", "pose_errors", "make_suite_scene", "write_suite_scene",
           "load_texture", "TEXTURES"]

_LIGHT = np.array([0.35, 0.85, 0.45]) / np.linalg.norm([0.35, 0.85, 0.45])
_AMBIENT = 0.5  # shade = ambient + (1 - ambient) |n . light|

# Texture name -> (skimage.data loader, tint for grey photographs or None)
TEXTURES = {
    "brick": ("brick", (0.85, 0.45, 0.32)),
    "gravel": ("gravel", (0.75, 0.7, 0.62)),
    "grass": ("grass", (0.45, 0.72, 0.3)),
    "coins": ("coins", (0.9, 0.78, 0.5)),
    "astronaut": ("astronaut", None),
    "chelsea": ("chelsea", None),
    "coffee": ("coffee", None),
    "rocket": ("rocket", None),
    "stars": ("hubble_deep_field", None),
}


@functools.lru_cache(maxsize=None)
def load_texture(name: str) -> np.ndarray:
    """Photograph ``name`` (a key of TEXTURES) as float64 RGB (H, W, 3) in [0, 1], read-only."""
    if name not in TEXTURES:
        raise ValueError(f"unknown texture {name!r}; choose one of {sorted(TEXTURES)}")
    try:
        import skimage.data
    except ImportError as e:  # pragma: no cover - a dependency of the package
        raise ImportError("the scene suite needs scikit-image (pip install scikit-image)") from e
    loader, tint = TEXTURES[name]
    img = np.asarray(getattr(skimage.data, loader)(), dtype=np.float64) / 255.0
    if img.ndim == 2:
        img = img[..., None] * np.asarray(tint)[None, None, :] / max(tint) * 1.1
    img = np.clip(img[..., :3], 0.0, 1.0)
    img.setflags(write=False)
    return img


# ============================================================================ geometry
@dataclass(frozen=True, eq=False)
class Patch:
    """A flat textured patch in its body frame: centre (3,), unit axes u, v (3,) (normal u x v),
    half extents (hu, hv), ``disk`` (an ellipse inscribed in the rectangle) or a rectangle, and the
    texture name with ``repeat`` copies along (u, v)."""

    centre: tuple
    u: tuple
    v: tuple
    half: tuple
    texture: str
    repeat: tuple = (1.0, 1.0)
    disk: bool = False


@dataclass(frozen=True, eq=False)
class Mover:
    """A rigid object: patches in its body frame and a motion body -> world at time t.

    kind: "tumble" (centre on a line plus a bob, rotating about ``axis`` by ``spin`` radians over
    the clip), "swing" (body origin at a hinge, angle amplitude ``spin`` at ``cycles`` per clip
    about ``axis``), "roll" (a disk of radius ``radius`` rolling along +x on the floor: spin =
    -distance / radius about ``axis``), "slide" (pure translation on a line, spin about ``axis``),
    "oscillate" (c(t) = origin + velocity sin(2 pi (cycles t + phase)): ``velocity`` is then the
    amplitude vector; turning by spin times the same sine). Otherwise centre c(t) = origin +
    velocity (t - 0.5) (+ a bob for tumble).
    """

    patches: tuple
    kind: str
    origin: tuple
    velocity: tuple = (0.0, 0.0, 0.0)
    axis: tuple = (0.0, 1.0, 0.0)
    spin: float = 0.0
    cycles: float = 1.0
    phase: float = 0.0
    radius: float = 1.0


def mover_pose(m: Mover, t: float):
    """(R body->world (3, 3), c (3,)) of mover m at time t."""
    o = np.asarray(m.origin, dtype=np.float64)
    vel = np.asarray(m.velocity, dtype=np.float64)
    axis = np.asarray(m.axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    c = o + vel * (t - 0.5)
    if m.kind == "tumble":
        c = c + np.array([0.0, 0.12 * np.sin(2 * np.pi * (m.cycles * t + m.phase)), 0.0])
        ang = m.spin * (t - 0.5)
    elif m.kind == "swing":
        ang = m.spin * np.sin(2 * np.pi * (m.cycles * t + m.phase))
    elif m.kind == "roll":
        ang = -float(vel[0]) * (t - 0.5) / m.radius
    elif m.kind == "slide":
        ang = m.spin * (t - 0.5)
    elif m.kind == "oscillate":
        c = o + vel * np.sin(2 * np.pi * (m.cycles * t + m.phase))
        ang = m.spin * np.sin(2 * np.pi * (m.cycles * t + m.phase))
    else:
        raise ValueError(f"unknown mover kind {m.kind!r}")
    return so3_exp(ang * axis), c


def _cube(centre, half, textures):
    """Six patches of an axis-aligned cube in a body frame centred at ``centre``."""
    c = np.asarray(centre, dtype=np.float64)
    faces = []
    e = np.eye(3)
    for a in range(3):
        for sgn in (1.0, -1.0):
            n = sgn * e[a]
            u = e[(a + 1) % 3]
            v = np.cross(n, u)
            faces.append(Patch(tuple(c + half * n), tuple(u), tuple(v), (half, half), textures[len(faces) % len(textures)]))
    return tuple(faces)


def _room(lo, hi, textures, repeats):
    """Inward faces of a box room: floor, ceiling, left, right, back, front."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    x, y, z = np.eye(3)
    spec = [  # (centre, u, v, (hu, hv))
        ((mid[0], lo[1], mid[2]), x, -z, (half[0], half[2])),  # floor, normal +y
        ((mid[0], hi[1], mid[2]), x, z, (half[0], half[2])),  # ceiling
        ((lo[0], mid[1], mid[2]), -z, y, (half[2], half[1])),  # left wall, normal +x
        ((hi[0], mid[1], mid[2]), z, y, (half[2], half[1])),  # right wall
        ((mid[0], mid[1], lo[2]), x, y, (half[0], half[1])),  # back wall, normal +z
        ((mid[0], mid[1], hi[2]), -x, y, (half[0], half[1])),  # behind the camera
    ]
    return tuple(Patch(tuple(c), tuple(u), tuple(v), h, t, r)
                 for (c, u, v, h), t, r in zip(spec, textures, repeats))


# ============================================================================ config
DEPTH_PRIORS = ("none", "video", "monocular")  # SuiteConfig.depth_prior


@dataclass(frozen=True)
class SuiteConfig:
    """One suite scene. ``family`` picks the world (FAMILIES); the rest describe the video."""

    family: str = "photo_room"
    width: int = 240
    height: int = 135
    num_frames: int = 24
    exposure_fraction: float = 0.7  # exposure / frame interval in [0, 1]; 0 = sharp video
    subframes: int = 16
    # Area sampling (docs/method.md §10): sharp frames and test views cast supersample^2 rays per pixel;
    # each blur sub-frame casts blur_supersample^2, shifted within their cells per sub-frame when
    # stratify is on (16 sub-frames x 2 x 2 -> 8 x 8 positions per pixel over the exposure).
    # supersample=2, blur_supersample=2, stratify=False is the unfiltered 2 x 2 suite (docs/results.md §4).
    supersample: int = 8
    blur_supersample: int = 2
    stratify: bool = True
    pan: float = 0.8  # sideways camera travel over the clip (world units)
    yaw_deg: float = 30.0  # the camera turns this much (degrees, about the vertical) over the clip
    shake: float = 1.0  # hand-shake amplitude scale (0 = tripod-smooth path)
    shake_cycles: float = 2.0  # hand-shake frequency, cycles per clip
    rot_noise_deg: float = 0.75  # RMS rotation error of the given poses (angle, degrees)
    trans_noise: float = 0.015  # RMS translation error of the given poses / scene depth
    drift: float = 0.5  # share of the pose-error variance that drifts (random walk) vs i.i.d.
    num_test_views: int = 4
    test_offset_fraction: float = 0.05  # test camera offset along its x axis / scene depth
    fov_x_deg: float = 60.0
    depth_prior: str = "none"  # "video" / "monocular": a modelled network's depth per frame (module docstring)
    prior_edge_px: float = 2.0  # its edge blur (Gaussian sigma, px at 240 px width; scaled with the width)
    prior_rel_error: float = 0.1  # its smooth relative error (standard deviation of the log)
    prior_shared_error: float = 0.0  # the share of that error's variance common to every frame
    seed: int = 0

    def __post_init__(self):
        check_choice(self.family, "SuiteConfig.family", tuple(sorted(FAMILIES)))
        check_int(self.width, "SuiteConfig.width", 16)
        check_int(self.height, "SuiteConfig.height", 16)
        check_int(self.num_frames, "SuiteConfig.num_frames", 2)
        check_int(self.subframes, "SuiteConfig.subframes", 1)
        check_int(self.supersample, "SuiteConfig.supersample", 1)
        check_int(self.blur_supersample, "SuiteConfig.blur_supersample", 1)
        check_bool(self.stratify, "SuiteConfig.stratify")
        check_int(self.num_test_views, "SuiteConfig.num_test_views", 0, self.num_frames, hint="at most num_frames")
        check_int(self.seed, "SuiteConfig.seed", 0)
        check_number(self.exposure_fraction, "SuiteConfig.exposure_fraction", 0.0, 1.0)
        if self.exposure_fraction > 0 and self.subframes < 2:
            raise ValueError("SuiteConfig.subframes must be >= 2 when exposure_fraction > 0; use >= 16 for "
                             "smooth blur, or exposure_fraction = 0 for a sharp video")
        check_number(self.shake, "SuiteConfig.shake", 0.0)
        for name in ("rot_noise_deg", "trans_noise"):
            check_number(getattr(self, name), f"SuiteConfig.{name}", 0.0, hint="pose noise")
        check_number(self.test_offset_fraction, "SuiteConfig.test_offset_fraction", 0.0)
        check_number(self.shake_cycles, "SuiteConfig.shake_cycles", 0.0, lo_open=True)
        check_number(self.drift, "SuiteConfig.drift", 0.0, 1.0)
        check_number(self.fov_x_deg, "SuiteConfig.fov_x_deg", 10.0, 120.0, hint="degrees")
        for name in ("pan", "yaw_deg"):
            check_number(getattr(self, name), f"SuiteConfig.{name}")
        check_choice(self.depth_prior, "SuiteConfig.depth_prior", DEPTH_PRIORS)
        check_number(self.prior_edge_px, "SuiteConfig.prior_edge_px", 0.0)
        check_number(self.prior_rel_error, "SuiteConfig.prior_rel_error", 0.0)
        check_number(self.prior_shared_error, "SuiteConfig.prior_shared_error", 0.0, 1.0)


# ============================================================================ worlds
@dataclass(frozen=True, eq=False)
class SuiteWorld:
    patches: tuple  # static Patch objects (world frame)
    movers: tuple  # Mover objects
    eye: np.ndarray  # (3,) camera position at mid-clip
    target: np.ndarray  # (3,) look-at point at mid-clip
    depth: float  # scene depth: camera to back wall (pose noise and test offsets scale with it)
    textures: dict  # (patch id) -> resampled texture (h, w, 3)
    sway: np.ndarray  # sum-of-sines blocks (data/camera_paths.py)
    shake_pos: np.ndarray
    shake_rot: np.ndarray
    pan: float
    yaw: float  # radians over the clip


def _family_photo_room(rng):
    """A room of photographs, a static cube, no movers: brick back wall, gravel floor, star-field and
    portrait walls."""
    room = _room((-3.0, 0.0, -2.5), (3.0, 3.0, 6.0), ("gravel", "coins", "stars", "astronaut", "brick", "grass"),
                 ((3, 4), (2, 3), (2, 1), (2, 1), (3, 2), (1, 1)))
    box = _cube((1.2, 0.4, -1.2), 0.4, ("chelsea", "coffee", "rocket"))
    return room + box, (), (0.0, 1.4, 3.0), (0.0, 1.0, -1.5)


def _family_wall_disk(rng):
    """A brick wall over a gravel floor and a textured disk rolling across."""
    wall = _room((-4.0, 0.0, -2.0), (4.0, 3.5, 8.0), ("gravel", "gravel", "brick", "brick", "brick", "grass"),
                 ((4, 5), (4, 5), (3, 1), (3, 1), (4, 2), (1, 1)))
    r = 0.55
    disk = Mover((Patch((0, 0, 0.02), (1, 0, 0), (0, 1, 0), (r, r), "coffee", disk=True),
                  Patch((0, 0, -0.02), (-1, 0, 0), (0, 1, 0), (r, r), "rocket", disk=True)),
                 "roll", origin=(0.0, r, -0.6), velocity=(2.2, 0.0, 0.0), axis=(0, 0, 1), radius=r)
    return wall, (disk,), (0.0, 1.3, 3.2), (0.0, 0.9, -1.5)


def _family_cube_sign(rng):
    """A room with a tumbling photo cube and a sign swinging on a hinge."""
    room = _room((-3.0, 0.0, -2.5), (3.0, 3.0, 6.0), ("gravel", "grass", "brick", "coins", "brick", "grass"),
                 ((3, 4), (2, 3), (2, 1), (2, 1), (3, 2), (1, 1)))
    cube = Mover(_cube((0, 0, 0), 0.35, ("chelsea", "coffee", "rocket", "astronaut", "stars", "coins")),
                 "tumble", origin=(-0.8, 1.0, -0.8), velocity=(0.8, 0.0, 0.3), axis=(0.4, 1.0, 0.3),
                 spin=2 * np.pi * 0.9, cycles=1.0, phase=float(rng.uniform()))
    sign = Mover((Patch((0, -0.45, 0.01), (1, 0, 0), (0, 1, 0), (0.5, 0.32), "astronaut", (1.0, 0.64)),
                  Patch((0, -0.45, -0.01), (-1, 0, 0), (0, 1, 0), (0.5, 0.32), "rocket")),
                 "swing", origin=(1.1, 2.3, -1.4), axis=(1, 0, 0), spin=0.6, cycles=1.2,
                 phase=float(rng.uniform()))
    return room, (cube, sign), (0.0, 1.4, 3.0), (0.0, 1.1, -1.5)


def _family_crossing(rng):
    """A star-field and photo room; a card enters from the left and leaves on the right."""
    room = _room((-3.0, 0.0, -2.5), (3.0, 3.0, 6.0), ("gravel", "coins", "brick", "chelsea", "stars", "grass"),
                 ((3, 4), (2, 3), (2, 1), (1, 1), (2, 1), (1, 1)))
    card = Mover((Patch((0, 0, 0.01), (1, 0, 0), (0, 1, 0), (0.45, 0.3), "chelsea"),
                  Patch((0, 0, -0.01), (-1, 0, 0), (0, 1, 0), (0.45, 0.3), "coffee")),
                 "slide", origin=(0.0, 1.1, 0.0), velocity=(6.0, 0.2, 0.0), axis=(0, 1, 0), spin=0.8)
    return room, (card,), (0.0, 1.3, 3.0), (0.0, 1.0, -1.5)


def _family_big_mover(rng):
    """Low-frequency content (smooth photographs seen large) and a large panel, covering about a
    quarter of the frame, swaying quickly left and right in front of it."""
    room = _room((-4.0, 0.0, -2.0), (4.0, 3.5, 8.0), ("coffee", "chelsea", "rocket", "coffee", "chelsea", "grass"),
                 ((1, 1), (1, 1), (1, 1), (1, 1), (1, 1), (1, 1)))
    panel = Mover((Patch((0, 0, 0.01), (1, 0, 0), (0, 1, 0), (0.75, 0.55), "astronaut", (1.0, 0.73)),
                   Patch((0, 0, -0.01), (-1, 0, 0), (0, 1, 0), (0.75, 0.55), "rocket")),
                  "oscillate", origin=(-0.3, 1.0, 1.2), velocity=(0.35, 0.05, 0.0), axis=(0, 1, 0), spin=0.25,
                  cycles=1.0, phase=float(rng.uniform()))
    return room, (panel,), (0.0, 1.3, 3.2), (0.0, 1.0, -1.5)


FAMILIES = {
    "photo_room": _family_photo_room,
    "wall_disk": _family_wall_disk,
    "cube_sign": _family_cube_sign,
    "crossing": _family_crossing,
    "big_mover": _family_big_mover,
}

# The suite: one preset per family, each a different kind of video. These describe the world;
# they are not tuned to what the method can fit.
SUITE = {
    # a hand-held sweep across a room of photographs: turning 40 deg, moderate shake
    "photo_room": SuiteConfig(family="photo_room", exposure_fraction=0.6, pan=0.8, yaw_deg=40.0, shake=1.0,
                              shake_cycles=2.0),
    # a slow pan along a brick wall while a disk rolls across
    "wall_disk": SuiteConfig(family="wall_disk", exposure_fraction=0.7, pan=1.2, yaw_deg=25.0, shake=0.6,
                             shake_cycles=1.5),
    # a shaky hand-held view of a tumbling cube and a swinging sign
    "cube_sign": SuiteConfig(family="cube_sign", exposure_fraction=0.8, pan=0.6, yaw_deg=30.0, shake=1.5,
                             shake_cycles=2.5),
    # strong, fast hand shake at a full-interval exposure; a card crosses the frame; drifting pose error
    "crossing": SuiteConfig(family="crossing", exposure_fraction=1.0, pan=0.4, yaw_deg=15.0, shake=2.0,
                            shake_cycles=3.0, drift=0.8),
    # a slow, steady pan over large smooth content; a large panel sways fast in front: object blur
    "big_mover": SuiteConfig(family="big_mover", exposure_fraction=0.8, pan=1.5, yaw_deg=15.0, shake=0.3,
                             shake_cycles=1.0, drift=0.2),
}


def _intrinsics(config: SuiteConfig):
    return fov_intrinsics(config.width, config.height, config.fov_x_deg)


def _resample(img, texels_u, texels_v):
    """Area-resample a photograph to (texels_v, texels_u), at least 2 x 2."""
    import cv2

    w, h = max(int(round(texels_u)), 2), max(int(round(texels_v)), 2)
    interp = cv2.INTER_AREA if w < img.shape[1] else cv2.INTER_CUBIC
    return np.clip(cv2.resize(np.ascontiguousarray(img), (w, h), interpolation=interp), 0.0, 1.0)


def build_suite_world(config: SuiteConfig) -> SuiteWorld:
    """The seeded world of ``config``: patches, movers, camera path and resampled textures."""
    if not isinstance(config, SuiteConfig):
        raise TypeError(f"config must be a SuiteConfig; got {type(config).__name__}")
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, 11]))
    patches, movers, eye, target = FAMILIES[config.family](rng)
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    back = min(p.centre[2] for p in patches)  # the back wall's z
    depth = float(eye[2] - back)
    fx = _intrinsics(config)[0, 0]
    textures = {}
    all_patches = list(patches) + [p for m in movers for p in m.patches]
    for i, p in enumerate(all_patches):
        # one texel = half a pixel at the patch's reference distance (its distance from the mid-clip eye,
        # at least 1): pixel-scale detail without minification aliasing
        dist = max(float(np.linalg.norm(np.asarray(p.centre) - eye)), 1.0)
        if i >= len(patches):  # mover patches: body frame; use the mover's origin
            m = next(m for m in movers if p in m.patches)
            dist = max(float(np.linalg.norm(np.asarray(m.origin) - eye)), 1.0)
        texel = 0.5 * dist / fx
        img = load_texture(p.texture)
        textures[i] = _resample(img, 2 * p.half[0] / p.repeat[0] / texel, 2 * p.half[1] / p.repeat[1] / texel)
    sway = random_sines(rng, [[0.05, 0.04, 0.05], [0.02, 0.02, 0.02]], [0.7, 1.3])
    shake_pos = random_sines(rng, [[0.01, 0.01, 0.006]], [config.shake_cycles])
    # hand shake: ~0.6 deg of tilt and pan, ~0.3 deg of roll, 1 cm of position at shake = 1
    shake_rot = random_sines(rng, [[0.01, 0.01, 0.005]], [config.shake_cycles * 1.1])
    shake_pos[:, 0, :] *= config.shake
    shake_rot[:, 0, :] *= config.shake
    return SuiteWorld(patches=tuple(patches), movers=tuple(movers), eye=eye, target=target, depth=depth,
                      textures=textures, sway=sway, shake_pos=shake_pos, shake_rot=shake_rot, pan=config.pan,
                      yaw=float(np.deg2rad(config.yaw_deg)))


def suite_camera_pose(world: SuiteWorld, t):
    """True cam_T_world at time(s) t: scalar -> (4, 4), (M,) -> (M, 4, 4). C-infinity in t."""
    t = as_times(t)
    tt = np.atleast_1d(t)
    eye = world.eye[None] + np.outer(tt - 0.5, [world.pan, 0.0, 0.0]) + eval_sines(world.sway, tt) \
        + eval_sines(world.shake_pos, tt)
    # the viewing direction turns smoothly about the vertical by yaw over the clip
    a = world.yaw * (tt - 0.5)
    look = world.target - world.eye
    target = eye + np.stack([look[0] * np.cos(a) + look[2] * np.sin(a), np.full_like(a, look[1]),
                             -look[0] * np.sin(a) + look[2] * np.cos(a)], axis=1)
    poses = shaken_look_at(eye, target, eval_sines(world.shake_rot, tt))
    return poses[0] if t.ndim == 0 else poses


def _intersect(patches, first_id, origin, dirs, depth, pid, local):
    """Nearest hits of rays o + s d (s > 0, s < depth) with ``patches`` (in the rays' frame).
    Updates depth (R,), pid (R,) and local (2, R) in place."""
    dx, dy, dz = dirs
    for j, p in enumerate(patches):
        c, u, v = (np.asarray(a, dtype=np.float64) for a in (p.centre, p.u, p.v))
        n = np.cross(u, v)
        denom = dx * n[0] + dy * n[1] + dz * n[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = float(n @ (c - origin)) / denom
        cand = (s > 1e-9) & (s < depth)  # NaN/inf (ray parallel to the plane) compare False
        if not np.any(cand):
            continue
        idx = np.flatnonzero(cand)
        sc = s[idx]
        rel = [origin[a] - c[a] + sc * dirs[a][idx] for a in range(3)]
        a = rel[0] * u[0] + rel[1] * u[1] + rel[2] * u[2]
        b = rel[0] * v[0] + rel[1] * v[1] + rel[2] * v[2]
        if p.disk:
            inside = (a / p.half[0]) ** 2 + (b / p.half[1]) ** 2 <= 1.0
        else:
            inside = (np.abs(a) <= p.half[0]) & (np.abs(b) <= p.half[1])
        idx, sc, a, b = idx[inside], sc[inside], a[inside], b[inside]
        depth[idx] = sc
        pid[idx] = first_id + j
        local[0, idx] = a
        local[1, idx] = b


def _sample(tex, p, a, b):
    """Bilinear, wrapped texture lookup at local patch coordinates (a, b): (3, M)."""
    h, w, _ = tex.shape
    x = (a / (2 * p.half[0]) + 0.5) * w * p.repeat[0] - 0.5
    y = (0.5 - b / (2 * p.half[1])) * h * p.repeat[1] - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = x - x0, y - y0
    x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    out = (tex[y0, x0].T * ((1 - fx) * (1 - fy)) + tex[y0, x1].T * (fx * (1 - fy))
           + tex[y1, x0].T * ((1 - fx) * fy) + tex[y1, x1].T * (fx * fy))
    return out


def _hits(world: SuiteWorld, origin, dirs, t):
    """Nearest hits of rays: depth (R,), patch id (R,) (-1: none; static patches first, then each
    mover's in order), local patch coordinates (2, R) and each patch's world normal at time t."""
    R = len(dirs[0])
    depth = np.full(R, np.inf)
    pid = np.full(R, -1, dtype=np.int64)
    local = np.zeros((2, R))
    _intersect(world.patches, 0, origin, dirs, depth, pid, local)
    normals = {i: np.cross(p.u, p.v) for i, p in enumerate(world.patches)}
    first = len(world.patches)
    for m in world.movers:
        Rm, c = mover_pose(m, t)
        o_b = Rm.T @ (origin - c)
        d_b = tuple(Rm[0, a] * dirs[0] + Rm[1, a] * dirs[1] + Rm[2, a] * dirs[2] for a in range(3))
        _intersect(m.patches, first, o_b, d_b, depth, pid, local)
        for j, p in enumerate(m.patches):
            normals[first + j] = Rm @ np.cross(p.u, p.v)
        first += len(m.patches)
    return depth, pid, local, normals


def _cast(world: SuiteWorld, origin, dirs, t):
    """rgb (3, R), depth (R,) (camera z for d = R^T (x, y, 1)), moving (R,) bool."""
    R = len(dirs[0])
    depth, pid, local, normals = _hits(world, origin, dirs, t)
    rgb = np.zeros((3, R))
    all_patches = list(world.patches) + [p for m in world.movers for p in m.patches]
    for i in np.flatnonzero(np.bincount(pid[pid >= 0], minlength=len(all_patches))):
        sel = np.flatnonzero(pid == i)
        shade = _AMBIENT + (1 - _AMBIENT) * abs(float(normals[i] @ _LIGHT))
        rgb[:, sel] = _sample(world.textures[i], all_patches[i], local[0, sel], local[1, sel]) * shade
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return rgb, depth, pid >= len(world.patches)


def render_suite_view(world: SuiteWorld, cam_T_world, t, K, width, height, supersample=8, offset=(0.0, 0.0)):
    """Sharp ray-cast image (H, W, 3) and moving-pixel mask (H, W) at a pose and time
    (``raycast.cast_view``: supersample^2 rays per pixel, shifted by ``offset`` within their cells)."""
    return cast_view(lambda origin, dirs: _cast(world, origin, dirs, float(t)), cam_T_world, K, width, height,
                     supersample, offset)


def suite_depth_map(world: SuiteWorld, cam_T_world, t, K, width, height):
    """True depth (H, W) through pixel centres at time t (inf where nothing is hit)."""
    return cast_depth(lambda origin, dirs: _cast(world, origin, dirs, float(t)), cam_T_world, K, width, height)


def mover_point_tracks(world: SuiteWorld, cam_T_world, K, t, pixels, poses, Ks, times):
    """Where the moving surface points seen at ``pixels`` (P, 2) (continuous, our convention) of a
    view (cam_T_world, K) at time t are in other views (poses (M, 4, 4), Ks (M, 3, 3), times (M,)):
    (M, P, 2) pixels, NaN where the pixel sees no mover or the point is behind that camera. The
    ground truth against which a dynamic object's tracked or initialised motion is measured
    (``examples/motion_init_accuracy.py``); occlusion in the other views is not checked."""
    T = np.asarray(cam_T_world, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    Rc = T[:3, :3]
    d_cam = np.stack([(px[:, 0] - K[0, 2]) / K[0, 0], (px[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(px))])
    dirs = tuple(Rc[0, a] * d_cam[0] + Rc[1, a] * d_cam[1] + Rc[2, a] * d_cam[2] for a in range(3))
    origin = -Rc.T @ T[:3, 3]
    depth, pid, _, _ = _hits(world, origin, dirs, float(t))
    X = origin[:, None] + depth[None] * np.stack(dirs)  # (3, P); inf where nothing is hit
    body = np.full((3, len(px)), np.nan)
    owner = np.full(len(px), -1)
    first = len(world.patches)
    for j, m in enumerate(world.movers):
        on = (pid >= first) & (pid < first + len(m.patches))
        Rm, c = mover_pose(m, float(t))
        body[:, on] = Rm.T @ (X[:, on] - c[:, None])
        owner[on] = j
        first += len(m.patches)
    out = np.full((len(times), len(px), 2), np.nan)
    for q, (P, Kq, tq) in enumerate(zip(np.asarray(poses, dtype=np.float64), np.asarray(Ks, dtype=np.float64),
                                        np.asarray(times, dtype=np.float64))):
        for j, m in enumerate(world.movers):
            on = owner == j
            if not on.any():
                continue
            Rm, c = mover_pose(m, float(tq))
            uv, z = project_points((Rm @ body[:, on] + c[:, None]).T, P, Kq)
            uv[~(z > 1e-9)] = np.nan
            out[q, on] = uv
    return out


def mover_tracks_of_seeds(world: SuiteWorld, frames, seed_frames, seed_pixels):
    """``mover_point_tracks`` for points seen at pixels seed_pixels (P, 2) of frames seed_frames (P,)
    of a scene's ``frames``: (M, P, 2) pixels in every frame, NaN where unknown."""
    poses = np.stack([f.cam_T_world for f in frames])
    Ks = np.stack([f.K for f in frames])
    times = np.array([f.time for f in frames])
    seed_frames = np.asarray(seed_frames)
    out = np.full((len(frames), len(seed_frames), 2), np.nan)
    for k in np.unique(seed_frames):
        sel = np.flatnonzero(seed_frames == k)
        f = frames[int(k)]
        out[:, sel] = mover_point_tracks(world, f.cam_T_world, f.K, f.time, np.asarray(seed_pixels)[sel], poses, Ks,
                                         times)
    return out


def pose_errors(num_frames, rot_rms_deg, trans_rms, drift, rng):
    """Pose-error tangents delta (N, 6) = (rho, phi): RMS |phi| = rot_rms_deg (as radians), RMS |rho| =
    trans_rms, a share ``drift`` of each variance from a normalised random walk, the rest i.i.d."""
    def part(kind):
        if kind == "iid":
            x = rng.normal(size=(num_frames, 3))
        else:
            x = np.cumsum(rng.normal(size=(num_frames, 3)), axis=0)
            x -= x.mean(axis=0)
        rms = np.sqrt(np.mean(np.sum(x * x, axis=1)))
        return x / rms if rms > 0 else x

    rho = np.sqrt(1 - drift) * part("iid") + np.sqrt(drift) * part("walk")
    phi = np.sqrt(1 - drift) * part("iid") + np.sqrt(drift) * part("walk")
    # the two parts are independent draws; renormalise so the RMS is exactly the one asked for
    rho *= trans_rms / max(np.sqrt(np.mean(np.sum(rho * rho, axis=1))), 1e-300)
    phi *= np.deg2rad(rot_rms_deg) / max(np.sqrt(np.mean(np.sum(phi * phi, axis=1))), 1e-300)
    return np.concatenate([rho, phi], axis=1)


def resolve(preset, seed=None, **overrides) -> SuiteConfig:
    """SuiteConfig of a suite preset name (or a SuiteConfig) with ``seed`` and field overrides."""
    base, overrides = preset_overrides(SuiteConfig, SUITE, preset, seed, overrides, what="suite preset")
    if overrides.get("exposure_fraction", base.exposure_fraction) == 0.0:
        overrides.setdefault("subframes", 1)  # a sharp video is rendered once per frame
    if "num_frames" in overrides:  # fewer frames than test views: one test view per frame at most
        overrides.setdefault("num_test_views", min(base.num_test_views, overrides["num_frames"]))
    return dataclasses.replace(base, **overrides)


def generate_suite(config: SuiteConfig) -> Scene:
    """Render the suite scene of ``config`` in memory."""
    world = build_suite_world(config)
    n = config.num_frames
    times = np.linspace(0.0, 1.0, n)
    tau = config.exposure_fraction / (n - 1)
    gt = suite_camera_pose(world, times)
    delta = pose_errors(n, config.rot_noise_deg, config.trans_noise * world.depth, config.drift,
                        np.random.default_rng(np.random.SeedSequence([config.seed, 12])))
    exact = not (config.rot_noise_deg > 0 or config.trans_noise > 0)
    est = gt.copy() if exact else se3_exp(delta) @ gt
    scene = render_clip(
        lambda t: suite_camera_pose(world, t),
        lambda T, t, K, W, H, ss, offset=(0.0, 0.0): render_suite_view(world, T, t, K, W, H, ss, offset),
        times=times, tau=tau, subframes=config.subframes, est_poses=est, K=_intrinsics(config),
        width=config.width, height=config.height, supersample=config.supersample,
        blur_supersample=config.blur_supersample, stratify=config.stratify,
        depth_fn=lambda T, t, K, W, H: suite_depth_map(world, T, t, K, W, H),
        num_test_views=config.num_test_views, test_offset=config.test_offset_fraction * world.depth,
        exposure_fraction=config.exposure_fraction, scene_scale=world.depth)
    if exact:
        scene.poses_trusted = True  # the given poses are the true ones (docs/dataset_format.md §4)
    if config.depth_prior != "none":
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, 31]))
        clip_scale = np.exp(rng.uniform(-1.0, 1.0))
        shared = None
        if config.prior_shared_error > 0:  # its own stream: the per-frame draws stay those without it
            shared = (config.prior_shared_error,
                      _unit_field(np.random.default_rng(np.random.SeedSequence([config.seed, 32])),
                                  config.height, config.width))
        for f in scene.frames:
            f.depth_prior = modelled_depth_prior(f.depth, rng, config.prior_edge_px * config.width / 240.0,
                                                 config.prior_rel_error, config.depth_prior, clip_scale, shared)
    return scene


def _unit_field(rng, H, W):
    """A unit-variance random field (H, W) smooth over an eighth of the width."""
    import cv2

    field = cv2.GaussianBlur(rng.normal(size=(H, W)), (0, 0), W / 8.0, borderType=cv2.BORDER_REFLECT)
    return field / max(float(field.std()), 1e-300)


def modelled_depth_prior(depth, rng, edge_px: float, rel_error: float, kind: str = "video", clip_scale=1.0,
                         shared=None):
    """A modelled depth network's output for a true depth map (H, W; inf = nothing hit): the
    module docstring's model; ``kind`` "video" (depth times ``clip_scale``) or "monocular"
    (disparity up to a scale and shift drawn here); ``shared``: (share c, unit field (H, W)), the
    error field then sqrt(1 - c) x this frame's own + sqrt(c) x the shared one. NaN where nothing
    is hit; positive elsewhere."""
    import cv2

    depth = np.asarray(depth, dtype=np.float64)
    H, W = depth.shape
    hit = np.isfinite(depth) & (depth > 0)
    if not hit.any():
        raise ValueError("monocular_depth_prior: the depth map hits nothing")
    disp = np.where(hit, 1.0 / np.where(hit, depth, 1.0), 0.0)
    if edge_px > 0:
        # normalised convolution: the blur mixes neighbouring surfaces, not the empty background
        w = cv2.GaussianBlur(hit.astype(np.float64), (0, 0), edge_px, borderType=cv2.BORDER_REFLECT)
        disp = cv2.GaussianBlur(disp, (0, 0), edge_px, borderType=cv2.BORDER_REFLECT) / np.maximum(w, 1e-12)
    if rel_error > 0:
        field = _unit_field(rng, H, W)
        if shared is not None and shared[0] > 0:
            if np.shape(shared[1]) != (H, W):
                raise ValueError(f"modelled_depth_prior: the shared field is {np.shape(shared[1])}, the depth {(H, W)}")
            field = np.sqrt(1.0 - shared[0]) * field + np.sqrt(shared[0]) * np.asarray(shared[1])
        disp = disp * np.exp(rel_error * field)
    if kind == "video":
        return np.where(hit, clip_scale / np.where(hit, disp, 1.0), np.nan)
    scale = np.exp(rng.uniform(-1.0, 1.0)) / float(np.median(disp[hit]))
    shift = rng.uniform(0.0, 0.3)
    return np.where(hit, scale * disp + shift, np.nan)


def make_suite_scene(preset="cube_sign", seed=None, **overrides) -> Scene:
    """In-memory suite scene ``preset`` with ``seed`` and SuiteConfig field overrides."""
    return generate_suite(resolve(preset, seed, **overrides))


def write_suite_scene(out_dir, preset="cube_sign", seed=None, overwrite=False, **overrides) -> Path:
    """Generate a suite scene and write it as a scene folder, with ``suite_config.json`` beside it."""
    from d2gs_np.data.io import write_scene

    config = resolve(preset, seed, **overrides)
    out = Path(out_dir)
    write_scene(generate_suite(config), out, overwrite=overwrite)
    (out / "suite_config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
    return out
