"""The scene's configs (d2gs_np/scene/config.py): defaults construct, and every bad field is refused
on construction with an error that names it."""
import dataclasses

import pytest

from d2gs_np.scene.config import WARPS, DeformConfig, InitConfig, MotionInitConfig, StereoConfig


@pytest.mark.parametrize("cls", [DeformConfig, InitConfig, StereoConfig, MotionInitConfig])
def test_defaults_construct_and_are_frozen(cls):
    config = cls()
    field = dataclasses.fields(cls)[0].name
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(config, field, getattr(config, field))


def test_deform_config_counts_its_coefficients():
    assert DeformConfig(degree=3, order=2).num_coefs == 7
    assert DeformConfig(degree=0, order=0).num_coefs == 0


@pytest.mark.parametrize("cls, bad, exc, match", [
    (DeformConfig, dict(degree=-1), ValueError, "degree"),
    (DeformConfig, dict(order=1.5), ValueError, "order"),
    (DeformConfig, dict(omega=0.0), ValueError, "omega"),
    (DeformConfig, dict(omega=float("nan")), ValueError, "omega"),
    (InitConfig, dict(frame_skips=(0,)), ValueError, "frame_skips"),
    (InitConfig, dict(dynamic_depth_factor=1.5), ValueError, "dynamic_depth_factor"),
    (InitConfig, dict(fill_depth_percentiles=(90.0, 10.0)), ValueError, "fill_depth_percentiles"),
    (InitConfig, dict(max_scale_px=-1.0), ValueError, "max_scale_px"),
    (InitConfig, dict(depth_range_mad=-1.0), ValueError, "depth_range_mad"),
    (InitConfig, dict(stereo=None), TypeError, "InitConfig.stereo must be a StereoConfig"),
    (InitConfig, dict(features=None), TypeError, "InitConfig.features must be a FeatureConfig"),
    (StereoConfig, dict(window=4), ValueError, "window must be odd"),
    (StereoConfig, dict(num_depths=2), ValueError, "num_depths"),
    (StereoConfig, dict(distinct_px=-1.0), ValueError, "distinct_px"),
    (StereoConfig, dict(distinct_px=float("inf")), ValueError, "distinct_px"),
    (MotionInitConfig, dict(min_area_fraction=1.5), ValueError, "MotionInitConfig.min_area_fraction"),
    (MotionInitConfig, dict(max_jump_fraction=0.0), ValueError, "MotionInitConfig.max_jump_fraction"),
    (MotionInitConfig, dict(ridge=-1.0), ValueError, "MotionInitConfig.ridge"),
    (MotionInitConfig, dict(ridge=0.0), ValueError, "MotionInitConfig.ridge"),
    (MotionInitConfig, dict(warp="affine"), ValueError, "MotionInitConfig.warp must be one of"),
    (MotionInitConfig, dict(rigid_fit="icp"), ValueError, "MotionInitConfig.rigid_fit must be one of"),
    (MotionInitConfig, dict(rigid="yes"), ValueError, "MotionInitConfig.rigid must be true or false"),
    (MotionInitConfig, dict(rigid_residual=1), ValueError, "MotionInitConfig.rigid_residual must be true or false"),
])
def test_bad_fields_are_refused_by_name(cls, bad, exc, match):
    with pytest.raises(exc, match=match):
        cls(**bad)


@pytest.mark.parametrize("warp", WARPS)
def test_every_warp_is_accepted(warp):
    assert MotionInitConfig(warp=warp).warp == warp
