"""Scene model: static and dynamic Gaussian sets, their deformation, and the map to renderer inputs."""
from d2gs_np.scene.config import DeformConfig
from d2gs_np.scene.deformation import deform_basis, deform_bwd, deform_fwd
from d2gs_np.scene.gaussians import (
    DEFORM_FIELDS,
    DYNAMIC,
    GAUSSIAN_FIELDS,
    STATIC,
    append_gaussians,
    has_dynamic,
    init_params,
    logit,
    make_gaussians,
    neighbour_log_scales,
    num_dynamic,
    num_static,
    opacity_bwd,
    opacity_fwd,
    prune,
    scale_bwd,
    scale_fwd,
    sigmoid,
    validate_params,
)
from d2gs_np.scene.render_inputs import RENDER_FIELDS, render_inputs_bwd, render_inputs_fwd

__all__ = [
    "DeformConfig", "deform_basis", "deform_fwd", "deform_bwd",
    "STATIC", "DYNAMIC", "GAUSSIAN_FIELDS", "DEFORM_FIELDS",
    "sigmoid", "logit", "opacity_fwd", "opacity_bwd", "scale_fwd", "scale_bwd",
    "neighbour_log_scales", "make_gaussians", "init_params", "validate_params",
    "has_dynamic", "num_static", "num_dynamic", "prune", "append_gaussians",
    "RENDER_FIELDS", "render_inputs_fwd", "render_inputs_bwd",
]
