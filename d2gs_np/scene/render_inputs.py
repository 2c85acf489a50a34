"""Scene parameters -> renderer inputs at one time, and the backward of that map.

``render_inputs_fwd`` turns the unconstrained parameter blocks (``d2gs_np.scene.gaussians``) into
what the renderer consumes (docs/conventions.md §1): means, raw-or-unit wxyz quats, linear scales,
post-sigmoid opacities, plain RGB colours, with the static rows first and the dynamic rows,
deformed to time t (``d2gs_np.scene.deformation``), after them.

Static quaternions are passed raw (the renderer normalises them); dynamic ones come out of the
deformation already unit length. A scene with rigid clusters (``scene/rigid.py``) then carries
each clustered dynamic Gaussian by its cluster's pose at t. A scene without a dynamic set does no
deformation work and returns v_t = 0.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import _check_time, _deform_bwd, _deform_fwd
from d2gs_np.scene.rigid import rigid_bwd, rigid_fwd
from d2gs_np.scene.gaussians import (
    CLUSTER,
    DYNAMIC,
    has_rigid,
    STATIC,
    has_dynamic,
    opacity_bwd,
    opacity_fwd,
    scale_bwd,
    scale_fwd,
    validate_params,
)

__all__ = ["RENDER_FIELDS", "render_inputs_fwd", "render_inputs_bwd"]

RENDER_FIELDS = ("means", "quats", "scales", "opacities", "colors")
_RENDER_TRAILING = {"means": (3,), "quats": (4,), "scales": (3,), "opacities": (), "colors": (3,)}


def render_inputs_fwd(params, t, deform_config):
    """Renderer inputs of the whole scene at time ``t``.

    params: scene parameter dict (layout in ``d2gs_np.scene.gaussians``).
    t: real scalar, normalised time (only the dynamic set depends on it).
    deform_config: DeformConfig; its K must match the dynamic coefficient blocks.

    Returns (render_inputs, saved) with render_inputs = dict(means (N, 3), quats (N, 4) wxyz,
    scales (N, 3) linear, opacities (N,), colors (N, 3)), N = Ns + Nd, static rows first. The
    arrays are new (never views of ``params``) and have the dtype of the params.
    """
    if not isinstance(deform_config, DeformConfig):
        raise TypeError(f"deform_config must be a DeformConfig; got {type(deform_config).__name__}")
    validate_params(params, deform_config)
    return _render_inputs_fwd(params, _check_time(t), deform_config)


def _render_inputs_fwd(params, t, deform_config):
    """``render_inputs_fwd`` without validation: ``params`` follows the layout (``validate_params``)
    with K = deform_config.num_coefs, ``t`` is a finite float. The private fast path of the
    trainer's step, whose model is validated once when it is built or loaded."""
    dynamic = has_dynamic(params)
    prefixes = (STATIC, DYNAMIC) if dynamic else (STATIC,)

    scales, scale_saved = scale_fwd(np.concatenate([params[f"{p}.log_scales"] for p in prefixes]))
    opacities, opacity_saved = opacity_fwd(np.concatenate([params[f"{p}.opacity_logits"] for p in prefixes]))
    means = [params[f"{STATIC}.means"]]
    quats = [params[f"{STATIC}.quats"]]
    colors = [params[f"{STATIC}.colors"]]
    deform_saved = rigid_saved = None
    if dynamic:
        (d_means, d_quats, d_colors), deform_saved = _deform_fwd(
            params[f"{DYNAMIC}.means"],
            params[f"{DYNAMIC}.quats"],
            params[f"{DYNAMIC}.colors"],
            params[f"{DYNAMIC}.deform_means"],
            params[f"{DYNAMIC}.deform_quats"],
            params[f"{DYNAMIC}.deform_colors"],
            t,
            deform_config,
        )
        if has_rigid(params):
            (d_means, d_quats), rigid_saved = rigid_fwd(d_means, d_quats, params[CLUSTER], params, t, deform_config)
        means.append(d_means)
        quats.append(d_quats)
        colors.append(d_colors)
    render_inputs = dict(
        means=np.concatenate(means),
        quats=np.concatenate(quats),
        scales=scales,
        opacities=opacities,
        colors=np.concatenate(colors),
    )
    saved = dict(
        num_static=params[f"{STATIC}.means"].shape[0],
        dtype=params[f"{STATIC}.means"].dtype,
        scale=scale_saved,
        opacity=opacity_saved,
        deform=deform_saved,
        rigid=rigid_saved,
    )
    return render_inputs, saved


def render_inputs_bwd(saved, v_render_inputs):
    """Gradients of the parameter blocks (and of t) from the cotangents of the renderer inputs.

    v_render_inputs: dict with any of means (N, 3), quats (N, 4), scales (N, 3), opacities (N,),
        colors (N, 3); a missing key (or None) counts as zero.

    Returns (v_params, v_t): v_params is keyed like the params given to ``render_inputs_fwd`` (every
    trained block, dense; not the cluster ids); v_t is the scalar derivative w.r.t. time (0 without
    a dynamic set), of the params' dtype.
    """
    if not isinstance(v_render_inputs, dict):
        raise TypeError(f"v_render_inputs must be a dict; got {type(v_render_inputs).__name__}")
    unknown = sorted(set(v_render_inputs) - set(RENDER_FIELDS))
    if unknown:
        raise ValueError(f"v_render_inputs has unknown keys {unknown}; expected a subset of {list(RENDER_FIELDS)}")
    dtype = saved["dtype"]
    N = saved["scale"].shape[0]
    for field in RENDER_FIELDS:
        shape = (N,) + _RENDER_TRAILING[field]
        x = v_render_inputs.get(field)
        if x is None:
            continue
        if not isinstance(x, np.ndarray) or x.dtype != dtype:
            got = x.dtype if isinstance(x, np.ndarray) else type(x).__name__
            raise TypeError(f"v_render_inputs[{field!r}] must be a {dtype} array like the params; got {got}")
        if x.shape != shape:
            raise ValueError(f"v_render_inputs[{field!r}] must have shape {shape}; got {x.shape}")
        dyn = x[saved["num_static"]:]  # the deformation's backward checks its (dynamic) rows
        if saved["deform"] is not None and field in ("means", "quats", "colors") and not np.all(np.isfinite(dyn)):
            raise ValueError(f"v_render_inputs[{field!r}] contains NaN or inf in its dynamic rows; every entry "
                             "must be finite")
    return _render_inputs_bwd(saved, v_render_inputs)


def _render_inputs_bwd(saved, v_render_inputs):
    """``render_inputs_bwd`` without validation (cotangents finite, of the params' dtype and shape)."""
    Ns, dtype = saved["num_static"], saved["dtype"]
    N = saved["scale"].shape[0]
    v = {}
    for field in RENDER_FIELDS:
        x = v_render_inputs.get(field)
        v[field] = np.zeros((N,) + _RENDER_TRAILING[field], dtype=dtype) if x is None else x

    v_log_scales = scale_bwd(saved["scale"], v["scales"])
    v_logits = opacity_bwd(saved["opacity"], v["opacities"])
    v_params = {
        f"{STATIC}.means": v["means"][:Ns].copy(),
        f"{STATIC}.log_scales": np.ascontiguousarray(v_log_scales[:Ns]),
        f"{STATIC}.quats": v["quats"][:Ns].copy(),
        f"{STATIC}.opacity_logits": np.ascontiguousarray(v_logits[:Ns]),
        f"{STATIC}.colors": v["colors"][:Ns].copy(),
    }
    v_t = dtype.type(0.0)
    if saved["deform"] is not None:
        v_dm, v_dq = v["means"][Ns:], v["quats"][Ns:]
        v_rigid, v_t_rigid = {}, dtype.type(0.0)
        if saved.get("rigid") is not None:
            v_dm, v_dq, v_rigid, v_t_rigid = rigid_bwd(saved["rigid"], v_dm, v_dq)
        g = _deform_bwd(saved["deform"], v_dm, v_dq, v["colors"][Ns:])
        v_params.update(v_rigid)
        v_params.update({
            f"{DYNAMIC}.means": g["base_means"],
            f"{DYNAMIC}.log_scales": np.ascontiguousarray(v_log_scales[Ns:]),
            f"{DYNAMIC}.quats": g["base_quats"],
            f"{DYNAMIC}.opacity_logits": np.ascontiguousarray(v_logits[Ns:]),
            f"{DYNAMIC}.colors": g["base_colors"],
            f"{DYNAMIC}.deform_means": g["coef_means"],
            f"{DYNAMIC}.deform_quats": g["coef_quats"],
            f"{DYNAMIC}.deform_colors": g["coef_colors"],
        })
        v_t = dtype.type(g["t"] + v_t_rigid)
    return v_params, v_t
