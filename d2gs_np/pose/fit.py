"""Fit one camera pose to an image on a frozen scene: the test-view protocol of BARF and
BAD-Gaussians (``d2gs eval --test-pose-opt N``, docs/method.md §10).

Novel views are scored after carrying each true test pose into the reconstruction's frame with a
similarity fitted on the training trajectory. Any residual error of that similarity, or of the
reconstruction's own frame, shows up as a misaligned render and a low PSNR that says nothing
about the scene. The common protocol therefore refines each test camera's pose against its
image, with the scene frozen, for a fixed number of steps, and scores the render at the refined
pose. Both numbers are reported, labelled (``nvs`` and ``nvs_pose_opt``).

Method: the pose is T = exp(xi) T_0 (a LEFT perturbation, xi = (rho, phi), translation first, as
in ``geometry.se3``). Each step renders at T, takes the mean squared error against the target,
its gradient to the 4x4 pose from the renderer's backward, maps that to the left tangent
(``matrix_grad_to_left_tangent``), takes an Adam step in the tangent at the current pose and
retracts: T <- exp(-step) T. Rotation steps are ``lr`` radians; translation steps ``lr`` times
the median rendered depth at T_0, so a step moves the image about as far either way and the
rate does not depend on the scene's units. The pose with the lowest error seen is returned
(the first candidate is T_0 itself, so the fit never scores worse than no fit).
"""
from __future__ import annotations


import numpy as np

from d2gs_np.geometry.se3 import check_rigid, matrix_grad_to_left_tangent, se3_exp, se3_inverse, se3_log
from d2gs_np.pose.config import PoseFitConfig
from d2gs_np.render import render_bwd, render_fwd

__all__ = ["fit_pose"]


def fit_pose(render_inputs, pose0, K, width, height, target, background=None, config: PoseFitConfig = None,
             render_config=None):
    """Refine ``pose0`` (4, 4 cam_T_world) so that the render of the frozen scene matches ``target``.

    render_inputs: dict with means, quats, scales, opacities, colors (float64), as from
        ``scene.render_inputs.render_inputs_fwd`` at the view's time.
    K (3, 3), width, height: the view's camera; target (H, W, 3) in [0, 1]; background (3,) or None (black);
    render_config: the renderer's RenderConfig (None: its default), as the scene is rendered for scoring.
    Returns (pose (4, 4), info): info has "mse" (steps + 1,) the error at each visited pose (index
    0: pose0), "best_step" and "xi" (6,), the left perturbation from pose0 to the returned pose.
    """
    config = PoseFitConfig() if config is None else config
    if not isinstance(config, PoseFitConfig):
        raise TypeError(f"config must be a PoseFitConfig; got {type(config).__name__}")
    T = np.array(pose0, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"pose0 must have shape (4, 4); got {T.shape}")
    check_rigid(T, "pose0")
    target = np.asarray(target, dtype=np.float64)
    if target.shape != (height, width, 3):
        raise ValueError(f"target must have shape ({height}, {width}, 3); got {target.shape}")
    if not np.all(np.isfinite(target)):
        raise ValueError("target contains NaN or inf")
    bg = np.zeros(3) if background is None else np.asarray(background, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    ri = {k: render_inputs[k] for k in ("means", "quats", "scales", "opacities", "colors")}
    n_pix = float(target.size)

    def loss_and_grad(pose, need_grad=True):
        out, saved = render_fwd(**ri, cam_T_world=pose, K=K, width=width, height=height, background=bg,
                                config=render_config)
        r = out["image"] - target
        mse = float(np.mean(r * r))
        if not need_grad:
            return mse, None, out
        g = render_bwd(saved, v_image=(2.0 / n_pix) * r)["cam_T_world"]
        return mse, matrix_grad_to_left_tangent(pose, np.asarray(g, np.float64)), out

    mse0, g, out0 = loss_and_grad(T, need_grad=config.steps > 0)
    depth = out0["expected_depth"][out0["alpha"] > 0.5]
    d = float(np.median(depth)) if depth.size else 1.0
    d = d if np.isfinite(d) and d > 0 else 1.0
    lr = np.array([config.lr * d] * 3 + [config.lr] * 3)
    b1, b2 = config.betas
    m, v = np.zeros(6), np.zeros(6)
    history = [mse0]
    best = (mse0, T.copy(), 0)
    for step in range(1, config.steps + 1):
        if not np.all(np.isfinite(g)):  # nothing sensible to follow (never seen; a guard, not a path)
            break
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        mhat, vhat = m / (1 - b1 ** step), v / (1 - b2 ** step)
        delta = lr * mhat / (np.sqrt(vhat) + config.eps)
        T = se3_exp(-delta) @ T
        last = step == config.steps
        mse, g, _ = loss_and_grad(T, need_grad=not last)
        history.append(mse)
        if mse < best[0]:
            best = (mse, T.copy(), step)
    pose = best[1]
    xi = se3_log(pose @ se3_inverse(np.asarray(pose0, np.float64)))
    return pose, {"mse": np.array(history), "best_step": best[2], "xi": xi}
