"""d2gs export-trajectory: a run's optimised poses as a TUM trajectory, camera-to-world with OpenCV
axes, read back exactly (docs/dataset_format.md §10)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from d2gs_np.cli import main
from d2gs_np.evaluation.runs import load_run
from d2gs_np.geometry.se3 import se3_exp
from d2gs_np.importers.tum import read_tum, write_tum

ROUND_TRIP_TOL = 1e-12  # floats written shortest-repr; only the quaternion <-> matrix rounding remains (~1e-16)


def _check_tum_columns(path, stamps, cam_T_world):
    """The file's columns against an independent reading: position = camera centre -R^T t,
    SciPy's scalar-last quaternion = the camera-to-world rotation R^T."""
    rows = np.loadtxt(path, comments="#")
    assert rows.shape == (len(stamps), 8)
    assert np.array_equal(rows[:, 0], stamps)
    for row, T in zip(rows, cam_T_world):
        R, t = T[:3, :3], T[:3, 3]
        assert np.max(np.abs(row[1:4] - (-R.T @ t))) < ROUND_TRIP_TOL
        assert np.max(np.abs(Rotation.from_quat(row[4:8]).as_matrix() - R.T)) < ROUND_TRIP_TOL
        assert np.linalg.norm(row[4:8]) == pytest.approx(1.0, abs=1e-15)


def test_write_and_read_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    T = se3_exp(np.concatenate([rng.normal(scale=3.0, size=(7, 3)), rng.normal(scale=1.5, size=(7, 3))], 1))
    T[3] = se3_exp(np.array([0.1, 0.2, 0.3, np.pi - 1e-9, 0.0, 0.0]))  # near a half turn: w ~ 0
    stamps = np.sort(rng.uniform(0, 100, 7))
    write_tum(tmp_path / "t.txt", stamps, T)
    _check_tum_columns(tmp_path / "t.txt", stamps, T)
    back_t, back_T = read_tum(tmp_path / "t.txt")
    assert np.array_equal(back_t, stamps) and np.max(np.abs(back_T - T)) < ROUND_TRIP_TOL
    (tmp_path / "bad.txt").write_text("0 1 2 3 0 0 0\n")
    with pytest.raises(ValueError, match="line 1"):
        read_tum(tmp_path / "bad.txt")


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("tum")
    scene, run = root / "scene", root / "run"
    assert main(["make-scene", str(scene), "--preset", "dynamic", "--seed", "3",
                 "--frames", "5", "--width", "40", "--height", "24"]) == 0
    assert main(["train", str(scene), "--out", str(run), "--iters", "2", "--quiet"]) == 0
    return run


def test_export_trajectory_writes_the_optimised_mid_poses(tiny_run, tmp_path, capsys):
    model = load_run(tiny_run).model
    mids = model.mid_poses()
    assert main(["export-trajectory", str(tiny_run), str(tmp_path / "traj.txt")]) == 0
    _check_tum_columns(tmp_path / "traj.txt", model.times, mids)
    stamps, poses = read_tum(tmp_path / "traj.txt")
    assert np.array_equal(stamps, model.times) and np.max(np.abs(poses - mids)) < ROUND_TRIP_TOL
    # with the frame rate: seconds, frame k at k / fps
    assert main(["export-trajectory", str(tiny_run), str(tmp_path / "sec.txt"), "--fps", "30"]) == 0
    assert read_tum(tmp_path / "sec.txt")[0] == pytest.approx(np.arange(model.num_frames) / 30.0, abs=1e-15)
    capsys.readouterr()
    # refusals: no run, an output path that is a folder
    assert main(["export-trajectory", str(tmp_path / "none"), str(tmp_path / "x.txt")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["export-trajectory", str(tiny_run), str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
