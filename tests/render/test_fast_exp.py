"""The rasteriser's polynomial exp(-s) (d2gs_np/render/fast_exp.py) against numpy.exp."""
from __future__ import annotations

import numba
import numpy as np
import pytest

from d2gs_np import constants as C
from d2gs_np.render import fast_exp

# Error budget of exp_neg against numpy.exp: Taylor remainder < 5e-18 relative, ~14 Horner steps
# each rounding at 0.5 ulp of a value near 1 but mostly damped by powers of |r| <= 0.35, and exact
# scaling by 2^-k: a few ulp. 4 ulp (float64, vs numpy.exp, itself within 0.5 ulp) and 2 ulp
# (float32, vs the float64 exp rounded) bound the measured 3 and 1.1 ulp; a wrong coefficient or
# range reduction shows at >= 1e3 ulp.
EXP_ULP_F64 = 4.0
EXP_ULP_F32 = 2.0


@numba.njit
def _exp_neg_array(s, e):
    ec = fast_exp.unpack_exp_consts(e)
    out = np.empty_like(s)
    for i in range(s.size):
        out[i] = fast_exp.exp_neg(s[i], ec)
    return out


@pytest.mark.parametrize("dtype, max_ulp", [(np.float64, EXP_ULP_F64), (np.float32, EXP_ULP_F32)])
def test_inline_exp_within_a_few_ulp(dtype, max_ulp):
    """exp_neg(s) = exp(-s) over [0, EXP_ARG_MAX] (dense grid, every range-reduction step k and
    its boundaries), and the clamp keeps masked lanes finite (s < 0 -> 1, s > max -> exp(-max))."""
    ln2 = np.log(2.0)
    k_edges = (np.arange(13)[:, None] + 0.5) * ln2 + np.array([-1e-12, 0.0, 1e-12])
    s = np.concatenate([np.linspace(0.0, C.EXP_ARG_MAX, 400_001), k_edges.ravel()]).astype(dtype)
    s = s[(s >= 0) & (s <= C.EXP_ARG_MAX)]
    got = _exp_neg_array(s, fast_exp.exp_consts(dtype)).astype(np.float64)
    want = np.exp(-s.astype(np.float64))
    ulps = np.abs(got - want) / np.spacing(want.astype(dtype)).astype(np.float64)
    assert ulps.max() <= max_ulp, (ulps.max(), s[np.argmax(ulps)])
    edge = _exp_neg_array(np.array([-3.0, -0.0, 1e3, np.inf], dtype), fast_exp.exp_consts(dtype))
    assert edge[0] == 1 and edge[1] == 1
    assert np.all(np.isfinite(edge)) and edge[2] == edge[3] == _exp_neg_array(
        np.array([C.EXP_ARG_MAX], dtype), fast_exp.exp_consts(dtype))[0]
