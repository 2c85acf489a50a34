"""Issue #41, cases 7, 8, 9 and 11 through the command line: nonsense input is never accepted silently.

Each test makes a tiny scene (``d2gs make-scene``), plants one defect in its transforms.json, mask
files or config, and calls ``train`` or ``eval``. A refusal is one line on stderr naming the problem
and the fix, status 2, before any work: the existing run folder it is pointed at keeps every byte
and mtime. A warning is one line ``d2gs CMD: warning: ...`` naming the frames or values, the range
and why, and the run goes on (and keeps the warning in its log's notes).
"""
import hashlib
import json
import shutil

import cv2
import numpy as np
import pytest

from d2gs_np.cli import main

W, H, N = 40, 24, 5
ITERS = "2"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A clean scene and a run trained on it (the existing run folder refusals must not touch)."""
    root = tmp_path_factory.mktemp("input_checks")
    scene, run = root / "scene", root / "run"
    assert main(["make-scene", str(scene), "--preset", "dynamic", "--frames", str(N), "--width", str(W),
                 "--height", str(H)]) == 0
    assert main(["train", str(scene), "--out", str(run), "--iters", ITERS, "--quiet"]) == 0
    return scene, run


def _copy(base, tmp_path, edit=None, name="scene"):
    """A copy of the clean scene with ``edit(transforms_dict, folder)`` applied to transforms.json."""
    dst = tmp_path / name
    shutil.copytree(base[0], dst)
    if edit is not None:
        p = dst / "transforms.json"
        d = json.loads(p.read_text())
        edit(d, dst)
        p.write_text(json.dumps(d))
    return dst


def _snapshot(folder):
    return {p.relative_to(folder).as_posix(): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _cli(argv, capsys):
    status = main(argv)
    out, err = capsys.readouterr()
    return status, out, err.strip().splitlines()


def _refused(base, scene, capsys, *extra, command="train"):
    """Run ``train SCENE --out <the existing run> --overwrite``: status 2, one error line, the run folder
    untouched (--overwrite replaces a run only once the new one has its first checkpoint). Returns the
    error line (other stderr lines are warnings)."""
    run = base[1]
    before = _snapshot(run)
    argv = ["train", str(scene), "--out", str(run), "--iters", ITERS, "--quiet", "--overwrite", *extra] \
        if command == "train" \
        else ["eval", str(run), "--scene", str(scene)]
    status, _, err = _cli(argv, capsys)
    errors = [line for line in err if line.startswith(f"d2gs {command}: error: ")]
    assert status == 2, err
    assert len(errors) == 1 and all(" warning: " in line for line in err if line not in errors), err
    assert not any("Traceback" in line for line in err)
    assert _snapshot(run) == before  # no work: the existing run folder kept every byte and mtime
    return errors[0]


def _trained_with_warning(scene, tmp_path, capsys, *extra, command="train"):
    """Run ``train`` into a new folder: status 0, the run finished; returns the warning lines (each also in
    the run log's notes)."""
    run = tmp_path / "run"
    status, _, err = _cli(["train", str(scene), "--out", str(run), "--iters", ITERS, "--quiet", *extra], capsys)
    assert status == 0, err
    assert (run / "final.npz").exists()
    warnings = [line for line in err if line.startswith("d2gs train: warning: ")]
    assert warnings == err, err  # nothing else on stderr
    notes = json.loads((run / "log.json").read_text())["notes"]
    for line in warnings:
        assert "warning: " + line[len("d2gs train: warning: "):] in notes
    return warnings


def _set_all_poses(d, fn):
    for f in d["frames"]:
        for key in ("transform_matrix", "gt_transform_matrix", "gt_exposure_start", "gt_exposure_end"):
            if key in f:
                f[key] = fn(f[key])


# ------------------------------------------------------------------ case 7: intrinsics, outlier poses
@pytest.mark.parametrize("focal, side", [(1e-6, "below 0.175 px, a 179"), (1e9, "above 2.29e+05 px, a 0.01")])
def test_case7_focal_length_not_in_pixels_is_refused(base, tmp_path, capsys, focal, side):
    scene = _copy(base, tmp_path, lambda d, _: d.update(fl_x=focal, fl_y=focal))
    line = _refused(base, scene, capsys)
    assert f"frames[0] ('images/0000.png'): fl_x = {focal:g} px is {side} deg field of view over the 40 px width" \
        in line
    assert "not a focal length in pixels; convert it to pixels" in line


def test_case7_implausible_field_of_view_warns_and_trains(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: d.update(fl_x=1.0, fl_y=1.0))
    (line,) = _trained_with_warning(scene, tmp_path, capsys)
    assert "transforms.json: all 5 frames: fl_x, fl_y = 1, 1 px give a field of view of 174.3 x 170.5 deg" in line
    assert "outside the [1, 170] deg of a video camera (fl_x in [1.75, 2.29e+03], fl_y in [1.05, 1.38e+03] px)" \
        in line
    # evaluation reads the scene again: it says so too, and goes on
    status, _, err = _cli(["eval", str(tmp_path / "run")], capsys)
    assert status == 0 and err == [line.replace("d2gs train:", "d2gs eval:")]


def test_case7_principal_point_outside_the_image_warns_far_outside_is_refused(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: d.update(cx=50.0))
    (line,) = _trained_with_warning(scene, tmp_path, capsys)
    assert "all 5 frames: principal point cx = 50 px lies outside the image (0 to 40 px, its width)" in line
    far = _copy(base, tmp_path, lambda d, _: d.update(cy=1e5), name="far")
    line = _refused(base, far, capsys)
    assert "principal point cy = 100000 px lies 4.17e+03 image heights outside the 24 px image (more than 5 is " \
           "refused): give cx, cy in pixels of this image" in line


def test_case7_outlier_camera_is_refused_far_one_warned(base, tmp_path, capsys):
    def move(dist):
        def edit(d, _):
            d["frames"][2]["transform_matrix"][0][3] += dist
        return edit
    line = _refused(base, _copy(base, tmp_path, move(1e12), name="absurd"), capsys)
    assert "the camera centre of frames[2] ('images/0002.png') at 1e+12 from the cameras' median centre" in line
    assert "beyond the 1e+06 x refused" in line and "fix its transform_matrix" in line
    (line,) = _trained_with_warning(_copy(base, tmp_path, move(300.0), name="far"), tmp_path, capsys)
    assert "the camera centre of frames[2] ('images/0002.png') at 299 from the cameras' median centre" in line
    assert "above the 100 x of a plausible camera path" in line and "camera extent" in line


# ------------------------------------------------------------------ case 8: masks
def _rewrite_masks(scene, fn):
    # every mask of the scene, the training frames' and the test views' (one encoding per scene)
    for p in sorted(q for q in scene.rglob("*.png") if q.parent.name == "masks"):
        cv2.imwrite(str(p), fn(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)))


def test_case8_zero_one_masks_keep_the_dynamic_set(base, tmp_path, capsys):
    scene = _copy(base, tmp_path)
    _rewrite_masks(scene, lambda m: (m > 127).astype(np.uint8))  # 0/1: read as 0/255 they were empty
    assert _trained_with_warning(scene, tmp_path, capsys) == []
    notes = json.loads((tmp_path / "run" / "log.json").read_text())["notes"]
    assert "dynamic set: on (motion masks mark moving pixels)" in notes


def test_case8_a_frame_without_a_mask_is_refused_naming_it(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: d["frames"][3].pop("mask_path"))
    line = _refused(base, scene, capsys)
    assert line == ("d2gs train: error: 1 of the 5 training frames has no motion mask (frame 3 (images/0003.png)) "
                    "while the others have one, and the dynamic set needs a mask on every frame: add mask_path to "
                    "those frames (an all-zero mask where nothing moves), or train without the dynamic set "
                    "(--dynamic off)")
    # without the dynamic set the masks are not needed
    assert _trained_with_warning(scene, tmp_path, capsys, "--dynamic", "off") == []


def test_case8_masks_of_neither_encoding_are_refused(base, tmp_path, capsys):
    scene = _copy(base, tmp_path)
    _rewrite_masks(scene, lambda m: (m > 127).astype(np.uint8) * 100)
    line = _refused(base, scene, capsys)
    assert "holds the brightest pixel of the scene's motion masks, 100: neither 0/255 masks (moving > 127) nor " \
           "0/1 masks (moving = 1)" in line and "save the masks with 255 (or 1) = moving" in line


# ------------------------------------------------------------------ case 9: duplicates, times, config, flat input
def test_case9_duplicate_frame_entry_is_refused(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: d["frames"].append(dict(d["frames"][1])))
    line = _refused(base, scene, capsys)
    assert line == ("d2gs train: error: transforms.json frames[5] ('images/0001.png') repeats frames[1] "
                    "('images/0001.png'): the same image twice; each frame must appear once in 'frames', remove the "
                    "duplicate entry")


def test_case9_shared_timestamps_warn(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: d["frames"][2].update(time=d["frames"][1]["time"]))
    (line,) = _trained_with_warning(scene, tmp_path, capsys)
    assert line.startswith("d2gs train: warning: transforms.json: frames[1] ('images/0001.png') and frames[2] "
                           "('images/0002.png') share time 0.25; frames of one video have distinct times")


def test_case9_all_equal_timestamps_refused_with_moving_pixels(base, tmp_path, capsys):
    scene = _copy(base, tmp_path, lambda d, _: [f.update(time=0.5) for f in d["frames"]])
    line = _refused(base, scene, capsys)
    assert line == ("d2gs train: error: all 5 training frames have time 0.5, but the motion masks mark moving pixels "
                    "and the deformation model needs each frame's time: give frame k of N the time k / (N - 1) in "
                    "transforms.json, or train without the dynamic set (--dynamic off)")
    (line,) = _trained_with_warning(scene, tmp_path, capsys, "--dynamic", "off")
    assert "transforms.json: all 5 frames have time 0.5" in line


def test_case9_background_out_of_range_is_refused(base, tmp_path, capsys):
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps({"train": {"background": [5, -3, 1e9]}}))
    line = _refused(base, base[0], capsys, "--config", str(cfg))
    assert line == ("d2gs train: error: TrainConfig.background[0] must be a finite number in [0, 1] (an RGB colour: "
                    "0 black, 1 white); got 5")


def test_case9_learning_rate_above_one_warns(base, tmp_path, capsys):
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps({"train": {"lr": {"means": 1e6}}}))
    (line,) = _trained_with_warning(base[0], tmp_path, capsys, "--config", str(cfg))
    assert line.startswith("d2gs train: warning: LearningRates.means = 1e+06 above 1: Adam moves a parameter by "
                           "about its learning rate each step")
    cfg.write_text(json.dumps({"train": {"lr": {"colors": -0.1}}}))
    line = _refused(base, base[0], capsys, "--config", str(cfg))
    assert "LearningRates.colors must be a finite number >= 0 (0 freezes the block); got -0.1" in line


def test_case9_flat_black_input_is_refused_one_black_frame_warned(base, tmp_path, capsys):
    scene = _copy(base, tmp_path)
    black = np.zeros((H, W, 3), np.uint8)
    for p in sorted((scene / "images").glob("*.png")):
        cv2.imwrite(str(p), black)
    line = _refused(base, scene, capsys)
    assert line.startswith("d2gs train: error: every training image is one flat colour (frame 0: RGB 0, 0, 0): "
                           "there is nothing to reconstruct")
    one = _copy(base, tmp_path, name="one")
    cv2.imwrite(str(one / "images" / "0002.png"), black)
    (line,) = _trained_with_warning(one, tmp_path, capsys)
    assert line.startswith("d2gs train: warning: transforms.json: frames[2] ('images/0002.png') is one flat "
                           "colour (a black or blank export?)")


# ------------------------------------------------------------------ case 11: poses rounded by their export
def test_case11_poses_rounded_to_6_decimals_are_reorthonormalised(base, tmp_path, capsys):
    def round6(d, folder):
        _set_all_poses(d, lambda M: [[round(x, 6) for x in row] for row in M])
        p = folder / "transforms_test.json"
        t = json.loads(p.read_text())
        _set_all_poses(t, lambda M: [[round(x, 6) for x in row] for row in M])
        p.write_text(json.dumps(t))
    scene = _copy(base, tmp_path, round6)
    (line,) = _trained_with_warning(scene, tmp_path, capsys)
    assert line.startswith("d2gs train: warning: re-orthonormalised the poses of ")
    assert "rigid only up to rounding, largest deviation 1.1e-06" in line
    # evaluation of the clean run against the rounded scene goes on, saying so once (beside the note
    # that this folder is a copy of the run's scene: same images, issue #41 case 6)
    status, _, err = _cli(["eval", str(base[1]), "--scene", str(scene)], capsys)
    warns = [line for line in err if line.startswith("d2gs eval: warning: ")]
    notes = [line for line in err if line.startswith("d2gs eval: note: ")]
    assert status == 0 and len(warns) == 1 and warns[0].startswith("d2gs eval: warning: re-orthonormalised")
    assert len(warns) + len(notes) == len(err), err


@pytest.mark.parametrize("factor, what", [((1.01, 1.0, 1.0), "the singular values of R are in"),
                                          ((1.0, 1.0, -1.0), "det(R) = -1 <= 0, a reflection")])
def test_case11_a_matrix_that_is_not_a_rotation_is_refused(base, tmp_path, capsys, factor, what):
    def edit(d, _):
        M = np.array(d["frames"][1]["transform_matrix"])
        M[:3, :3] = M[:3, :3] @ np.diag(factor)
        d["frames"][1]["transform_matrix"] = M.tolist()
    line = _refused(base, _copy(base, tmp_path, edit), capsys)
    assert "transforms.json frames[1] ('images/0001.png'): 'transform_matrix' is not rigid: " + what in line
