"""Our outputs and gradients for a case's inputs (docs/refcheck.md §3).

``compute(kind, inputs, cotangents, dtype, renderer)`` evaluates one case with our
implementation: the renderer's ``render_fwd``/``render_bwd`` (docs/conventions.md §10), the blur
model (``d2gs_np.blur.render``) or the deformation (``d2gs_np.scene.deformation``), and returns
``(outputs, gradients)`` as dicts of arrays in the file layout. The export calls it in float64 with
the fast renderer; ``d2gs refcheck run`` calls it in any dtype and with either renderer, which
makes our own code a "port" that compare can check (the NumPy reference against the Numba path).
"""
from __future__ import annotations

import numpy as np

from d2gs_np.geometry.se3 import matrix_grad_to_left_tangent
from d2gs_np.render.config import RenderConfig

__all__ = ["compute", "resolve_renderer"]

RENDER_FIELDS = ("means", "quats", "scales", "opacities", "colors")
_IMAGE_KEYS = ("image", "alpha", "depth", "expected_depth")


def resolve_renderer(renderer):
    """"fast" (d2gs_np.render, Numba), "reference" (d2gs_np.reference, NumPy) or a module / object
    with render_fwd and render_bwd."""
    if renderer is None or renderer == "fast":
        from d2gs_np import render as mod
        return mod
    if renderer == "reference":
        from d2gs_np import reference as mod
        return mod
    if isinstance(renderer, str):
        raise ValueError(f"renderer must be 'fast' or 'reference' (or a module with render_fwd/render_bwd); "
                         f"got {renderer!r}")
    if not (callable(getattr(renderer, "render_fwd", None)) and callable(getattr(renderer, "render_bwd", None))):
        raise TypeError(f"renderer must provide render_fwd and render_bwd; got {renderer!r}")
    return renderer


def _config(inputs):
    return RenderConfig(near_plane=float(inputs["near_plane"]), far_plane=float(inputs["far_plane"]),
                        eps2d=float(inputs["eps2d"]), antialiased=bool(inputs["antialiased"]),
                        tile_size=int(inputs["tile_size"]))


def _cot_args(cot, dtype):
    """File-layout image cotangents (1,H,W,3) / (1,H,W,1) -> render_bwd's (H,W,3) / (H,W)."""
    return dict(v_image=np.ascontiguousarray(cot["image"][0], dtype=dtype),
                v_alpha=np.ascontiguousarray(cot["alpha"][0, ..., 0], dtype=dtype),
                v_depth=np.ascontiguousarray(cot["depth"][0, ..., 0], dtype=dtype),
                v_expected_depth=np.ascontiguousarray(cot["expected_depth"][0, ..., 0], dtype=dtype))


def _image_outputs(out):
    return {"image": out["image"][None], "alpha": out["alpha"][None, ..., None],
            "depth": out["depth"][None, ..., None], "expected_depth": out["expected_depth"][None, ..., None]}


def _compute_render(inputs, cot, dtype, renderer):
    cast = lambda k: np.ascontiguousarray(inputs[k], dtype=dtype)  # noqa: E731
    T = np.ascontiguousarray(inputs["viewmats"][0], dtype=dtype)
    out, saved = renderer.render_fwd(
        cast("means"), cast("quats"), cast("scales"), cast("opacities"), cast("colors"), T,
        np.ascontiguousarray(inputs["Ks"][0], dtype=dtype), int(inputs["width"]), int(inputs["height"]),
        np.ascontiguousarray(inputs["backgrounds"][0], dtype=dtype), config=_config(inputs))
    g = renderer.render_bwd(saved, **_cot_args(cot, dtype))
    outputs = _image_outputs(out)
    outputs.update(radii=np.asarray(out["radii"], np.int32)[None], means2d=out["means2d"][None],
                   depths=out["depths"][None], conics=out["conics"][None])
    grads = {k: g[k] for k in RENDER_FIELDS}
    grads.update(
        viewmats=g["cam_T_world"][None],
        viewmats_tangent=matrix_grad_to_left_tangent(np.asarray(T, np.float64),
                                                     np.asarray(g["cam_T_world"], np.float64))[None].astype(dtype),
        backgrounds=g["background"][None], means2d=g["means2d"][None])
    return outputs, grads


class _RenderLayoutScene:
    """Scene model for the blur case: its parameters are already renderer inputs (keys
    "static.means", ..., "static.colors" holding means, quats, linear scales, opacities, colours),
    so the blur model's evaluate step is the identity and its time derivative 0."""

    @staticmethod
    def render_inputs_fwd(params, t, deform_config):
        return {k: params[f"static.{k}"] for k in RENDER_FIELDS}, params["static.means"].dtype

    @staticmethod
    def render_inputs_bwd(saved, v):
        return {f"static.{k}": np.array(v[k], copy=True) for k in RENDER_FIELDS}, saved.type(0)


def _compute_blur(inputs, cot, dtype, renderer):
    from d2gs_np.blur.config import BlurConfig
    from d2gs_np.blur.render import blur_render_bwd, blur_render_fwd
    from d2gs_np.scene.config import DeformConfig

    cast = lambda k: np.ascontiguousarray(inputs[k], dtype=dtype)  # noqa: E731
    params = {f"static.{k}": cast(k) for k in RENDER_FIELDS}
    n = int(inputs["num_virtual"])
    out, saved = blur_render_fwd(
        params, 0.0, 0.0, np.ascontiguousarray(inputs["viewmats"][0], dtype=dtype), cast("xi_start"),
        cast("xi_end"), np.ascontiguousarray(inputs["Ks"][0], dtype=dtype), int(inputs["width"]),
        int(inputs["height"]), np.ascontiguousarray(inputs["backgrounds"][0], dtype=dtype), BlurConfig(n),
        DeformConfig(), render_config=_config(inputs), renderer=renderer, scene_model=_RenderLayoutScene)
    v_params, v_xs, v_xe, _, aux = blur_render_bwd(saved, **_cot_args(cot, dtype), return_aux=True)
    outputs = _image_outputs(out)
    outputs["viewmats_virtual"] = np.asarray(out["poses"])
    grads = {k: v_params[f"static.{k}"] for k in RENDER_FIELDS}
    grads.update(xi_start=np.asarray(v_xs), xi_end=np.asarray(v_xe),
                 virtual_tangents=np.asarray(aux["v_pose_tangents"]).astype(dtype))
    return outputs, grads


_DEFORM_INPUTS = ("base_means", "base_quats", "base_colors", "coef_means", "coef_quats", "coef_colors")


def _compute_deform(inputs, cot, dtype, renderer):
    from d2gs_np.scene.config import DeformConfig
    from d2gs_np.scene.deformation import deform_bwd, deform_fwd

    cfg = DeformConfig(degree=int(inputs["degree"]), order=int(inputs["order"]), omega=float(inputs["omega"]))
    args = [np.ascontiguousarray(inputs[k], dtype=dtype) for k in _DEFORM_INPUTS]
    # t is cast to the working dtype first, so a float32 port's t is the exported float32 value.
    t = float(np.asarray(inputs["t"], dtype=dtype))
    (means, quats, colors), saved = deform_fwd(*args, t, cfg)
    g = deform_bwd(saved, *(np.ascontiguousarray(cot[k], dtype=dtype) for k in ("means", "quats", "colors")))
    grads = {k: g[k] for k in _DEFORM_INPUTS}
    grads["t"] = np.asarray(g["t"], dtype=dtype)
    return {"means": means, "quats": quats, "colors": colors}, grads


_KINDS = {"render": _compute_render, "blur": _compute_blur, "deform": _compute_deform}


def compute(kind, inputs, cotangents, dtype=np.float64, renderer=None):
    """(outputs, gradients) of our implementation on one case, in the file layout, in ``dtype``.

    kind: "render", "blur" or "deform".  inputs, cotangents: dicts of arrays (file layout).
    renderer: "fast" (default), "reference" or a module with render_fwd / render_bwd.
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {sorted(_KINDS)}; got {kind!r}")
    dtype = np.dtype(dtype)
    if dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f"dtype must be float64 or float32; got {dtype}")
    return _KINDS[kind](inputs, cotangents, dtype, resolve_renderer(renderer))
