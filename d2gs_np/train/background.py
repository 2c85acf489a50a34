"""A random background behind each training step's render (``TrainConfig.random_background``).

Every pixel of a photograph sees a surface, but a model rendered over a fixed black background
can stand semi-transparent Gaussians in for dark colour (docs/method.md §10 measures how much).
From a new viewpoint such layers blend differently and the background shows through at the
frame's edges. A background drawn at
random each step makes any transmittance cost loss, so the model turns opaque where the photograph
is. The public Gaussian-splatting trainers offer the same option (3DGS's ``--random_background``,
gsplat's ``simple_trainer`` ``random_bkgd``).

The renderer composites over ``model.background`` (b0); re-compositing its output over b is
linear in alpha, so the render is not repeated:

    image_b = image_b0 + (1 - alpha) (b - b0)
    v_alpha = -sum_c v_image_b[..., c] (b - b0)[c],   v_image_b0 = v_image_b

With the blur model the image and alpha are the means over the virtual views, and the identity
holds for the means as it does for each view (every view of a step gets the same b).
"""
from __future__ import annotations

import numpy as np

__all__ = ["background_rng", "composite_fwd", "composite_bwd"]

_BACKGROUND_STREAM = 0xB6  # seed stream of the backgrounds (apart from the frame order's and the views')


def background_rng(seed: int, step: int) -> np.random.Generator:
    """The generator of step ``step``'s background: a function of (seed, step) only, so a resumed
    run draws what the uninterrupted one drew."""
    return np.random.default_rng((seed, step, _BACKGROUND_STREAM))


def composite_fwd(image, alpha, background, rendered_over):
    """image (H, W, 3) rendered over ``rendered_over`` (3,) with accumulated alpha (H, W), moved
    over ``background`` (3,). Returns the new image (H, W, 3)."""
    shift = np.asarray(background, dtype=image.dtype) - np.asarray(rendered_over, dtype=image.dtype)
    return image + (1.0 - alpha)[..., None] * shift


def composite_bwd(v_image, background, rendered_over):
    """Cotangent of alpha (H, W) from that of the composited image (H, W, 3); the image's own
    cotangent passes through unchanged."""
    shift = np.asarray(background, dtype=v_image.dtype) - np.asarray(rendered_over, dtype=v_image.dtype)
    return -(v_image @ shift)
