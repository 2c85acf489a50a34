"""A classical two-stage baseline: deblur each frame on its own, then train without a blur model.

The paper's Table II compares D²GS with "deblur the frames first, then reconstruct" pipelines
whose deblurring networks need weights we cannot fetch. This is the same idea with a method that
runs offline (docs/method.md §10): non-blind Richardson-Lucy deconvolution of each frame with a
linear motion kernel predicted from the given poses.

Kernel of frame k (``frame_blur_kernel``): the camera's velocity from its neighbours' estimated
poses, ``v = log(T_{k+1} T_{k-1}^-1) / (t_{k+1} - t_{k-1})`` (one-sided at the ends), moved over
the exposure ``tau`` (``exposure_fraction / (N - 1)``; 1/2 of the frame interval when the
scene does not say), carries the image centre's ray, at depth ``depth``, from pixel ``p0`` to
``p1``; the kernel is a line segment from ``-(p1 - p0)/2`` to ``+(p1 - p0)/2``, anti-aliased,
normalised to sum 1. One kernel per frame: a rotating camera's blur varies over the image and
moving objects blur in their own way, which a global kernel cannot follow: that is the
baseline's known weakness, as for the paper's two-stage methods.

``deblur_scene`` writes a copy of a scene folder whose images are deconvolved and whose
``exposure_fraction`` is 0 (so training leaves the blur model out); sharp frames, masks, poses
and test views are kept as they are, so evaluation is unchanged.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from d2gs_np.geometry.se3 import se3_exp, se3_inverse, se3_log

__all__ = ["motion_kernel", "frame_blur_kernel", "richardson_lucy", "deblur_scene"]

RL_ITERATIONS = 10  # Richardson-Lucy iterations of the two-stage baseline (PSNR per count: docs/results.md §14)
_KERNEL_SUPERSAMPLE = 8  # sub-pixel samples per pixel of the segment's length when drawing the kernel


def motion_kernel(dx: float, dy: float) -> np.ndarray:
    """(k, k) float64 kernel of a straight blur from -(dx, dy)/2 to +(dx, dy)/2 pixels, centred,
    drawn with bilinear splats of points spread evenly along the segment, summing to 1. A blur
    shorter than a pixel gives (nearly) the identity kernel; k is odd."""
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise ValueError(f"blur displacement must be finite; got ({dx}, {dy})")
    length = math.hypot(dx, dy)
    half = int(math.ceil(length / 2.0)) + 1
    k = 2 * half + 1
    ker = np.zeros((k, k))
    m = max(2, int(math.ceil(length * _KERNEL_SUPERSAMPLE)) + 1)
    for s in np.linspace(-0.5, 0.5, m):
        x, y = half + s * dx, half + s * dy
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        for yy, wy in ((y0, 1 - fy), (y0 + 1, fy)):
            for xx, wx in ((x0, 1 - fx), (x0 + 1, fx)):
                ker[yy, xx] += wx * wy
    return ker / ker.sum()


def frame_blur_kernel(poses, times, k: int, K, width: int, height: int, exposure_fraction, depth: float):
    """Motion kernel of frame k predicted from the estimated poses (module docstring).

    poses: (N, 4, 4) cam_T_world estimates; times: (N,); K: (3, 3); depth > 0: the depth of the
    image centre's scene point (e.g. the scene scale). Returns (kernel, (dx, dy)).
    """
    poses = np.asarray(poses, dtype=np.float64)
    times = np.asarray(times, dtype=np.float64)
    n = len(poses)
    if n < 2:
        raise ValueError(f"a blur kernel from poses needs at least 2 frames; got {n}")
    if not (depth > 0 and math.isfinite(depth)):
        raise ValueError(f"depth must be a positive finite number; got {depth}")
    a, b = max(0, k - 1), min(n - 1, k + 1)
    dt = times[b] - times[a]
    if dt <= 0:
        raise ValueError(f"frames {a} and {b} have non-increasing times {times[a]}, {times[b]}")
    v = se3_log(poses[b] @ se3_inverse(poses[a])) / dt  # left velocity of cam_T_world
    frac = 0.5 if exposure_fraction is None else float(exposure_fraction)
    tau = frac / (n - 1)
    K = np.asarray(K, dtype=np.float64)
    ray = np.linalg.solve(K, np.array([(width) / 2.0, (height) / 2.0, 1.0]))
    X = ray / ray[2] * depth  # the image centre's point, camera coordinates at mid-exposure

    def project(T):  # T acts on camera coordinates (a left perturbation of cam_T_world)
        x = T[:3, :3] @ X + T[:3, 3]
        if x[2] <= 1e-9 * depth:  # behind the camera: no meaningful kernel
            return None
        p = K @ (x / x[2])
        return p[:2]

    p0, p1 = project(se3_exp(-0.5 * tau * v)), project(se3_exp(0.5 * tau * v))
    if p0 is None or p1 is None:
        return motion_kernel(0.0, 0.0), (0.0, 0.0)
    d = p1 - p0
    return motion_kernel(float(d[0]), float(d[1])), (float(d[0]), float(d[1]))


def richardson_lucy(image, kernel, iterations: int = RL_ITERATIONS) -> np.ndarray:
    """Non-blind Richardson-Lucy deconvolution of an (H, W, 3) image in [0, 1], channel by channel
    (scikit-image's implementation), with reflected borders so edges do not ring; clipped to
    [0, 1]."""
    from skimage.restoration import richardson_lucy as rl

    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3); got {img.shape}")
    if not np.all(np.isfinite(img)):
        raise ValueError("image contains NaN or inf")
    pad = kernel.shape[0] // 2
    out = np.empty_like(img)
    for c in range(3):
        padded = np.pad(img[..., c], pad, mode="reflect") if pad else img[..., c]
        res = rl(np.clip(padded, 1e-6, 1.0), kernel, num_iter=int(iterations), clip=True)
        out[..., c] = res[pad:pad + img.shape[0], pad:pad + img.shape[1]] if pad else res
    return np.clip(out, 0.0, 1.0)


def deblur_scene(scene_dir, out_dir, iterations: int = RL_ITERATIONS, overwrite: bool = False) -> dict:
    """Write a deconvolved copy of a scene folder (module docstring). Returns a report: the blur
    length in pixels per frame and the input/output PSNR against the sharp frames when the scene
    has them."""
    from d2gs_np.evaluation import metrics
    from d2gs_np.data.io import load_scene, write_scene

    scene = load_scene(scene_dir)
    poses = np.stack([f.cam_T_world for f in scene.frames])
    times = np.array([f.time for f in scene.frames])
    depth = float(scene.scene_scale) if scene.scene_scale else 1.0
    frames, lengths, before, after = [], [], [], []
    for k, f in enumerate(scene.frames):
        ker, (dx, dy) = frame_blur_kernel(poses, times, k, f.K, f.width, f.height, scene.exposure_fraction, depth)
        img = richardson_lucy(f.image, ker, iterations)
        lengths.append(math.hypot(dx, dy))
        if f.sharp is not None:
            before.append(metrics.psnr(f.image, f.sharp))
            after.append(metrics.psnr(img, f.sharp))
        frames.append(dataclasses.replace(f, image=img))
    write_scene(dataclasses.replace(scene, frames=frames, exposure_fraction=0.0), Path(out_dir), overwrite=overwrite)
    report = {"blur_length_px": lengths}
    if before:
        report.update(input_psnr=float(np.mean(before)), deblurred_psnr=float(np.mean(after)))
    return report
