"""Gaussian splatting renderer: Numba fast path (see api.py)."""
