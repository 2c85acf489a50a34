"""The pose package's settings (d2gs_np/pose/config.py): each bad value is named, and loading the
settings pulls in no solver."""
import subprocess
import sys

import numpy as np
import pytest

from d2gs_np.pose.config import (CorrespondConfig, FeatureConfig, GaussNewtonConfig, PoseFitConfig, PoseInitConfig,
                                 TrackConfig)


def test_loading_the_pose_configs_imports_no_solver():
    # the experiment config nests these: reading one must not load OpenCV, CasADi or the Numba kernels
    code = ("import sys, d2gs_np.pose.config; "
            "print(','.join(m for m in ('cv2', 'casadi', 'numba') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


@pytest.mark.parametrize("cls, bad, exc, word", [
    (FeatureConfig, dict(ratio=1.5), ValueError, "ratio"),
    (FeatureConfig, dict(min_matches=5), ValueError, "min_matches"),
    (FeatureConfig, dict(detector="surf"), ValueError, "detector"),
    (CorrespondConfig, dict(gaps=(0,)), ValueError, "gaps"),
    (TrackConfig, dict(fb_px=0), ValueError, "fb_px"),
    (TrackConfig, dict(window_px=2), ValueError, "window_px"),
    (TrackConfig, dict(retry_window_px=2), ValueError, "retry_window_px"),
    (PoseInitConfig, dict(solver="lm"), ValueError, "PoseInitConfig.solver must be one of"),
    (PoseInitConfig, dict(mode="maybe"), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(min_views=1), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(fallback_min_views=1), ValueError, "PoseInitConfig.fallback_min_views"),
    (PoseInitConfig, dict(fallback_min_points=-1), ValueError, "PoseInitConfig.fallback_min_points"),
    (PoseInitConfig, dict(fallback_parallax_deg=0.0), ValueError, "PoseInitConfig.fallback_parallax_deg"),
    (PoseInitConfig, dict(prior_rot_deg=0.0), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(outlier_px=np.nan), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(max_nfev=0), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(tracks="klt"), TypeError, "PoseInitConfig"),
    (PoseInitConfig, dict(min_frame_observations=0), ValueError, "PoseInitConfig"),
    (PoseInitConfig, dict(smooth_trans_rel=-0.01), ValueError, "PoseInitConfig.smooth_trans_rel"),
    (PoseInitConfig, dict(smooth_trans_rel=np.inf), ValueError, "PoseInitConfig.smooth_trans_rel"),
    (GaussNewtonConfig, dict(robust="l1"), ValueError, "robust"),
    (GaussNewtonConfig, dict(beta=float("nan")), ValueError, "beta"),
    (PoseFitConfig, dict(steps=-1), ValueError, "steps"),
    (PoseFitConfig, dict(lr=0.0), ValueError, "lr"),
])
def test_bad_values_are_named(cls, bad, exc, word):
    with pytest.raises(exc, match=word):
        cls(**bad)
