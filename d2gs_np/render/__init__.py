"""Gaussian splatting renderer: Numba fast path (see api.py).

``render_fwd`` and ``render_bwd`` are loaded on first use, so that importing the configuration
(``d2gs_np.render.config``, plain data) does not import Numba.
"""
from d2gs_np.render.config import RenderConfig

__all__ = ["render_fwd", "render_bwd", "RenderConfig"]


def __getattr__(name):
    if name in ("render_fwd", "render_bwd"):
        from d2gs_np.render import api

        return getattr(api, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
