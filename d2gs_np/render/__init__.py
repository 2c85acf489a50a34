"""Gaussian splatting renderer: Numba fast path (see api.py)."""
from d2gs_np.render.api import render_bwd, render_fwd
from d2gs_np.render.config import RenderConfig

__all__ = ["render_fwd", "render_bwd", "RenderConfig"]
