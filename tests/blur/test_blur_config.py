"""Tests of the blur model's settings (d2gs_np.blur.config): a bad field fails when the config is
made, naming the field, and the module loads without the Numba kernels, OpenCV or CasADi."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from d2gs_np.blur.config import BlurConfig, TrajectoryConfig


def test_blur_config_refuses_bad_fields():
    with pytest.raises(ValueError, match="num_virtual"):
        BlurConfig(num_virtual=0)
    with pytest.raises(ValueError, match="n_schedule"):
        BlurConfig(n_schedule="sometimes")
    with pytest.raises(ValueError, match="view_spacing_px"):
        BlurConfig(n_schedule="length", view_spacing_px=0.0)
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="backward_views"):
            BlurConfig(backward_views=bad)


def test_trajectory_config_refuses_bad_fields():
    with pytest.raises(ValueError, match="kind must be one of"):
        TrajectoryConfig(kind="spline")
    with pytest.raises(ValueError, match="init_spread"):
        TrajectoryConfig(init_spread=0.0)
    with pytest.raises(ValueError, match="init"):
        TrajectoryConfig(init="zeros")
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="velocity_window"):
            TrajectoryConfig(velocity_window=bad)


def test_loading_the_blur_configs_imports_no_solver():
    # settings are plain data: reading them must not pull in CasADi, OpenCV or the Numba kernels
    code = ("import sys; import d2gs_np.blur.config; "
            "print(','.join(m for m in ('casadi', 'cv2', 'numba') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[2])
    assert out.stdout.strip() == "", f"importing d2gs_np.blur.config imports {out.stdout.strip()}"


def test_the_exposure_path_is_checked():
    from d2gs_np.blur.config import TrajectoryConfig
    from d2gs_np.blur.endpoints import XI_MID, init_trajectory, trajectory_block_names

    # "auto" (the default) renders as the geodesic until a run decides (train.components)
    assert TrajectoryConfig().path == "auto" and XI_MID not in trajectory_block_names(TrajectoryConfig())
    assert XI_MID not in trajectory_block_names(TrajectoryConfig(path="geodesic"))
    cfg = TrajectoryConfig(path="three_knot")
    assert trajectory_block_names(cfg)[-1] == XI_MID
    poses = np.stack([np.eye(4)] * 3)
    poses[:, 0, 3] = [0.0, 0.1, 0.2]
    blocks = init_trajectory(cfg, poses, np.linspace(0, 1, 3), np.random.default_rng(0))
    assert blocks[XI_MID].shape == (3, 6) and not blocks[XI_MID].any()  # the line through T̂ to start
    with pytest.raises(ValueError, match="TrajectoryConfig.path must be one of"):
        TrajectoryConfig(path="cubic")
    with pytest.raises(ValueError, match="'three_knot' needs kind 'direct'"):
        TrajectoryConfig(path="three_knot", kind="posenet")
