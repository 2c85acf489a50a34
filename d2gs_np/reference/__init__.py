"""Plain NumPy reference implementations (float64, obvious), used to test the fast paths.

``render_fwd`` / ``render_bwd``: the Gaussian splatting renderer of docs/conventions.md §10;
``render`` is an alias of ``render_fwd``.
"""
from d2gs_np.reference.render import render_bwd, render_fwd

render = render_fwd

__all__ = ["render_fwd", "render_bwd", "render"]
