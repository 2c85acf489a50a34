"""Named golden cases of the reference-check kit (docs/refcheck.md §2).

Each builder returns a :class:`Case`: its inputs in the file layout of docs/refcheck.md §3
(gsplat's argument layout for renders: a leading camera axis C = 1 on viewmats, Ks, backgrounds
and every image), the fixed upstream gradient (cotangent) of every output, and facts a port
needs to judge a mismatch (the scene's threshold margins, a conditioning factor). Our outputs
and gradients are computed from these inputs by ``d2gs_np.refcheck.compute``.

The stiff render cases are the ones of tests/render/test_render_fast.py and
tests/reference/test_render_reference.py, rebuilt here with the same seeds.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from d2gs_np import constants as C
from d2gs_np.refcheck.scenes import (camera_scene, extreme_anisotropy_scene, extreme_scales_scene, flat_covariance_scene,
                                     near_plane_scene, random_scene, safe_random_scene, threshold_margins)
from d2gs_np.render.config import RenderConfig

__all__ = ["Case", "CASES", "DEFAULT_CASES", "DEFAULT_CASES_F32", "build_case", "render_case_inputs"]

KINDS = ("render", "blur", "deform")


@dataclass
class Case:
    """One golden case.

    name: file stem.  kind: "render", "blur" or "deform".  description: one line.
    inputs: {name: array} in the file layout (docs/refcheck.md §3), float64.
    cotangents: {output name: array} the fixed upstream gradient, float64.
    margins: threshold margins of each rendered view (docs/refcheck.md §4); {} for "deform".
    condition: >= 1, the factor by which rounding is amplified in this case (the 2D covariance's
        condition number kappa times 1e-3 for needles, 1 otherwise); compare multiplies its
        relative tolerances by it.
    """

    name: str
    kind: str
    description: str
    inputs: dict
    cotangents: dict
    margins: dict = field(default_factory=dict)
    condition: float = 1.0


# ---------------------------------------------------------------------------------------------
# Layout helpers
# ---------------------------------------------------------------------------------------------


def render_case_inputs(scene, config=None):
    """Our render scene dict (render_fwd's arguments) -> the file layout of a "render" case."""
    cfg = RenderConfig() if config is None else config
    f64 = lambda x: np.array(x, dtype=np.float64)  # noqa: E731
    return {
        "means": f64(scene["means"]), "quats": f64(scene["quats"]), "scales": f64(scene["scales"]),
        "opacities": f64(scene["opacities"]), "colors": f64(scene["colors"]),
        "viewmats": f64(scene["cam_T_world"])[None], "Ks": f64(scene["K"])[None],
        "backgrounds": f64(scene["background"])[None],
        "width": np.array(int(scene["width"])), "height": np.array(int(scene["height"])),
        "near_plane": np.array(float(cfg.near_plane)), "far_plane": np.array(float(cfg.far_plane)),
        "eps2d": np.array(float(cfg.eps2d)), "tile_size": np.array(int(cfg.tile_size)),
        "antialiased": np.array(bool(cfg.antialiased)),
    }


def _image_cotangents(rng, width, height):
    """Random normal upstream gradients of image (1,H,W,3), alpha, depth, expected_depth (1,H,W,1)."""
    return {
        "image": rng.normal(size=(1, height, width, 3)),
        "alpha": rng.normal(size=(1, height, width, 1)),
        "depth": rng.normal(size=(1, height, width, 1)),
        "expected_depth": rng.normal(size=(1, height, width, 1)),
    }


def _render(name, description, scene, config=None, seed=0, condition=1.0):
    rng = np.random.default_rng(10_000 + seed)
    return Case(name, "render", description, render_case_inputs(scene, config),
                _image_cotangents(rng, int(scene["width"]), int(scene["height"])),
                margins={"view0": threshold_margins(scene, config)}, condition=float(condition))


# ---------------------------------------------------------------------------------------------
# Render cases
# ---------------------------------------------------------------------------------------------

MARGIN = 1e-4  # as tests/render/test_render_fast.py: far above float32 and float64 rounding


def _random_small():
    scene = safe_random_scene(np.random.default_rng(0), 8, 16, 16, margin=MARGIN)
    return _render("random_small", "8 random Gaussians, 16x16 (one tile)", scene, seed=0)


def _random_medium():
    scene = safe_random_scene(np.random.default_rng(1), 64, 48, 40, margin=MARGIN)
    return _render("random_medium", "64 random Gaussians, 48x40 (partial bottom tile row)", scene, seed=1)


def _random_large():
    # More Gaussians make a 1e-4 margin unlikely in one draw; 1e-5 is still 100x float32 rounding.
    scene = safe_random_scene(np.random.default_rng(2), 200, 64, 48, margin=1e-5, sigma_px_range=(1.0, 5.0))
    return _render("random_large", "200 random Gaussians, 64x48 (4x3 tiles)", scene, seed=2)


def _partial_tiles():
    scene = safe_random_scene(np.random.default_rng(4), 30, 17, 33, margin=MARGIN)
    return _render("partial_tiles", "30 Gaussians, 17x33: every tile column and row but one partial", scene, seed=4)


def _thin_image():
    scene = safe_random_scene(np.random.default_rng(27), 20, 1, 23, margin=MARGIN)
    return _render("thin_image", "20 Gaussians on a 1x23 image (one pixel wide)", scene, seed=27)


def _antialiased():
    cfg = RenderConfig(antialiased=True)
    scene = safe_random_scene(np.random.default_rng(10), 40, 29, 31, margin=MARGIN, config=cfg)
    return _render("antialiased", "40 Gaussians, 29x31, antialiased mode (opacity compensation)", scene, cfg,
                   seed=10)


def _other_config():
    cfg = RenderConfig(near_plane=1.0, eps2d=0.1, tile_size=7)
    scene = safe_random_scene(np.random.default_rng(12), 40, 30, 19, margin=MARGIN, config=cfg)
    return _render("other_config", "40 Gaussians, 30x19, near_plane 1, eps2d 0.1, tile_size 7", scene, cfg,
                   seed=12)


def _tile_border():
    rng = np.random.default_rng(3)
    W, H, f = 37, 23, 40.0
    uv = np.array([(16, 16), (32, 16), (16, 0), (0, 16), (32, 8), (8, 16), (37, 23), (24, 16.0)])
    z = np.linspace(2.0, 4.0, len(uv))
    p_c = np.stack([(uv[:, 0] - W / 2.0) * z / f, (uv[:, 1] - H / 2.0) * z / (f * 1.02), z], axis=1)
    sig = np.array([2.0, 3.0, 5.0, 4.0, 2.5, 3.5, 6.0, 3.0])[:, None] * z[:, None] / f * np.array([[1.0, 0.6, 1.4]])
    scene = camera_scene(p_c, sig, rng.uniform(0.3, 0.9, len(uv)), rng.uniform(0, 1, (len(uv), 3)), W, H, f=f,
                         rng=rng)
    scene["cam_T_world"] = np.eye(4)
    scene["means"] = p_c
    return _render("tile_border", "8 Gaussians centred on tile corners and edges of a 37x23 image", scene, seed=3)


def _extreme_scales():
    scene = extreme_scales_scene()
    return _render("extreme_scales", "scales log-uniform in [1e-6, 1e3]: dilation-only points to "
                   "Gaussians far larger than the image", scene, seed=21)


def _extreme_anisotropy():
    from d2gs_np import reference as ref

    scene = extreme_anisotropy_scene()
    _, saved = ref.render_fwd(**scene)
    cov, det = saved["proj"]["cov"], saved["proj"]["det"]
    kappa = float(np.max(cov[:, 0, 0] * cov[:, 1, 1] / det))
    # The det cancellation loses log10(kappa) digits in any implementation: rounding differences
    # grow like eps * kappa; tests/render/test_render_fast.py allows 1e-13 * kappa against 1e-10.
    return _render("extreme_anisotropy", f"needles and pancakes, scale ratios up to 1e9 (2D condition "
                   f"number {kappa:.2g}: tolerances x {max(1.0, 1e-3 * kappa):.3g})", scene, seed=22,
                   condition=max(1.0, 1e-3 * kappa))


def _near_plane():
    scene = near_plane_scene()
    return _render("near_plane", "z = 1.5 near (kept, huge footprint), z = near exactly, below near and "
                   "behind the camera (culled)", scene, seed=22)


def _flat_covariance():
    scene = flat_covariance_scene()
    return _render("flat_covariance", "singular 3D covariances: one, two or three scales exactly 0", scene,
                   seed=23)


def _opacity_extremes():
    rng = np.random.default_rng(24)
    n, W, H = 10, 22, 19
    p_c = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(2, 4, n)], axis=1)
    sig = rng.uniform(0.05, 0.3, (n, 3))
    p_c[3] = [0.013, -0.021, 1.5]
    sig[3] = [3.0, 2.0, 2.5]
    opac = rng.uniform(0.1, 0.9, n)
    opac[:3] = 0.0
    opac[3:6] = 1.0
    colors = rng.uniform(-2.0, 3.0, (n, 3))
    scene = camera_scene(p_c, sig, opac, colors, W, H, rng=rng)
    scene["background"] = np.array([-0.5, 1.5, 0.3])
    return _render("opacity_extremes", "opacity 0 and 1 (alpha clamped at 0.999 over many pixels, no "
                   "gradient through the clamp), colours and background outside [0, 1]", scene, seed=24)


def _opacity_cutoff():
    """Opacities 1e-3 (relative) above and below the 1/255 cut-off, each Gaussian's mean exactly on
    a pixel centre (sigma = 0 there, so that pixel's alpha is the opacity itself): the ones above
    are composited on their centre pixel only, the ones below nowhere; a wider opaque Gaussian
    behind them all. Every decision keeps a 1e-3 margin, far above float32 rounding."""
    W = H = 16
    f, cx = 16.0, 8.0
    K = np.array([[f, 0.0, cx], [0.0, f, cx], [0.0, 0.0, 1.0]])
    uv = np.array([(3.5, 3.5), (10.5, 4.5), (5.5, 11.5), (12.5, 12.5), (8.5, 8.5)])
    z = np.array([2.0, 2.5, 3.0, 3.5, 6.0])
    means = np.stack([(uv[:, 0] - cx) * z / f, (uv[:, 1] - cx) * z / f, z], axis=1)  # exact in binary
    cut = C.ALPHA_THRESHOLD
    opacities = np.array([cut * (1 + 1e-3), cut * (1 - 1e-3), cut * (1 + 1e-2), cut * (1 - 1e-2), 0.7])
    scales = np.array([[0.1, 0.12, 0.1], [0.15, 0.1, 0.1], [0.1, 0.1, 0.2], [0.2, 0.15, 0.1], [1.5, 1.2, 1.0]])
    rng = np.random.default_rng(29)
    scene = dict(means=means, quats=np.tile([1.0, 0.0, 0.0, 0.0], (5, 1)), scales=scales, opacities=opacities,
                 colors=rng.uniform(size=(5, 3)), cam_T_world=np.eye(4), K=K, width=W, height=H,
                 background=np.array([0.2, 0.3, 0.4]))
    return _render("opacity_cutoff", "opacities 1e-3 and 1e-2 above and below the 1/255 cut-off, means on pixel "
                   "centres: one pixel or none each", scene, seed=29)


def _covering_image():
    rng = np.random.default_rng(25)
    p_c = np.array([[0.0, 0.0, 2.0], [0.05, -0.02, 3.0]])
    sig = np.array([[5.0, 4.0, 3.0], [0.1, 0.2, 0.1]])
    scene = camera_scene(p_c, sig, [0.6, 0.8], rng.uniform(0, 1, (2, 3)), 33, 21, rng=rng)
    return _render("covering_image", "a Gaussian covering the whole 33x21 image, another in front", scene, seed=25)


def _many_on_one_pixel(n=100_000, o=0.01):
    """1e5 Gaussians of alpha exactly o on a 1x1 image (the mean on the pixel centre, so
    sigma = 0): the pixel stops after exactly 916 (0.99^917 <= 1e-4 < 0.99^916, ln ratio 916.4)."""
    rng = np.random.default_rng(0)
    z = 1.0 + 1e-3 * rng.permutation(n)  # distinct in float32, listed in random order
    K = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    scene = dict(means=np.stack([np.zeros(n), np.zeros(n), z], -1), quats=np.tile([1.0, 0, 0, 0], (n, 1)),
                 scales=np.full((n, 3), 0.1), opacities=np.full(n, o), colors=rng.uniform(size=(n, 3)),
                 cam_T_world=np.eye(4), K=K, width=1, height=1, background=np.array([0.3, 0.3, 0.3]))
    return _render("many_on_one_pixel", f"{n} Gaussians of alpha {o} on one pixel, in random depth order: "
                   "the compositing stops after exactly 916", scene, seed=26)


# ---------------------------------------------------------------------------------------------
# Blur and deformation cases
# ---------------------------------------------------------------------------------------------


def _blur():
    """A blurry frame: n = 8 virtual views on the SE(3) geodesic between exp(xi_start) T and
    exp(xi_end) T, the mean of 8 renders; every sub-frame render keeps margin >= 1e-5."""
    from d2gs_np.blur.virtual_poses import virtual_poses

    rng = np.random.default_rng(5)
    W = H = 24
    n = 8
    for _ in range(200):
        scene = random_scene(rng, 12, W, H)
        xs, xe = rng.normal(size=6) * 0.02, rng.normal(size=6) * 0.02
        poses = virtual_poses(scene["cam_T_world"], xs, xe, n)
        margins = {f"view{i}": threshold_margins(dict(scene, cam_T_world=T)) for i, T in enumerate(poses)}
        if min(min(m.values()) for m in margins.values()) >= 1e-5:
            break
    else:  # pragma: no cover - the seed above finds one
        raise RuntimeError("no blur case with margin >= 1e-5")
    inputs = render_case_inputs(scene)
    inputs.update(xi_start=xs, xi_end=xe, num_virtual=np.array(n))
    return Case("blur", "blur", "blurry frame: mean of 8 renders at virtual poses on the SE(3) geodesic "
                "between exp(xi_start) T and exp(xi_end) T, 12 Gaussians, 24x24",
                inputs, _image_cotangents(np.random.default_rng(10_005), W, H), margins=margins)


def _deform():
    """Polynomial (degree 2) + Fourier (order 2) deformation of 10 Gaussians at t = 0.37."""
    from d2gs_np.scene.config import DeformConfig

    rng = np.random.default_rng(6)
    cfg = DeformConfig(degree=2, order=2)
    n, k = 10, cfg.num_coefs
    inputs = {
        "base_means": rng.normal(size=(n, 3)), "base_quats": rng.normal(size=(n, 4)),
        "base_colors": rng.uniform(size=(n, 3)),
        "coef_means": 0.1 * rng.normal(size=(n, k, 3)), "coef_quats": 0.1 * rng.normal(size=(n, k, 4)),
        "coef_colors": 0.1 * rng.normal(size=(n, k, 3)),
        "t": np.array(0.37), "degree": np.array(cfg.degree), "order": np.array(cfg.order),
        "omega": np.array(float(cfg.omega)),
    }
    cot = {"means": rng.normal(size=(n, 3)), "quats": rng.normal(size=(n, 4)), "colors": rng.normal(size=(n, 3))}
    return Case("deform", "deform", "dynamic Gaussians' deformation A0 + poly(t) + Fourier(t), degree 2, "
                "order 2, 10 Gaussians, t = 0.37; gradients to bases, coefficients and t", inputs, cot)


CASES = {
    "random_small": _random_small,
    "random_medium": _random_medium,
    "random_large": _random_large,
    "partial_tiles": _partial_tiles,
    "thin_image": _thin_image,
    "tile_border": _tile_border,
    "antialiased": _antialiased,
    "other_config": _other_config,
    "extreme_scales": _extreme_scales,
    "extreme_anisotropy": _extreme_anisotropy,
    "near_plane": _near_plane,
    "flat_covariance": _flat_covariance,
    "opacity_extremes": _opacity_extremes,
    "opacity_cutoff": _opacity_cutoff,
    "covering_image": _covering_image,
    "many_on_one_pixel": _many_on_one_pixel,
    "blur": _blur,
    "deform": _deform,
}
DEFAULT_CASES = tuple(CASES)
# A float32 export leaves out extreme_anisotropy: its 2D covariance has condition number ~6e6,
# so float32 (eps 6e-8) keeps no correct digit of its determinant; any float32 port fails it
# (ours gives conics off by 1e17). It can still be exported in float32 by name.
FLOAT64_ONLY = ("extreme_anisotropy",)
DEFAULT_CASES_F32 = tuple(c for c in CASES if c not in FLOAT64_ONLY)


def build_case(name):
    """The named case (ValueError naming the known ones otherwise)."""
    if name not in CASES:
        raise ValueError(f"unknown refcheck case {name!r}; known cases: {', '.join(CASES)}")
    return CASES[name]()
