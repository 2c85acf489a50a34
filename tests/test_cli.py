"""The command line end to end on a tiny scene, and its errors (exit status 2, a message, no work)."""
import json

import numpy as np
import pytest

from d2gs_np.cli import main
from d2gs_np.data.ply import read_ply


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("cli")
    scene, run = root / "scene", root / "run"
    assert main(["make-scene", str(scene), "--preset", "dynamic", "--seed", "3",
                 "--frames", "5", "--width", "40", "--height", "24"]) == 0
    assert main(["train", str(scene), "--out", str(run), "--iters", "6", "--quiet"]) == 0
    return scene, run


def test_eval_writes_metrics_with_the_documented_keys(trained):
    scene, run = trained
    assert main(["eval", str(run)]) == 0
    m = json.loads((run / "metrics.json").read_text())
    for key in ("dvs", "nvs", "input_blur"):
        assert set(m[key]) >= {"psnr", "ssim", "flip"} and np.isfinite(m[key]["psnr"])
        assert 0.0 < m[key]["flip"] < 1.0  # perceptual difference of unequal images, lower is better
    assert set(m["trajectory"]) >= {"ate", "rpe_t", "rpe_r", "initial"}
    assert set(m["trajectory"]["initial"]) == {"ate", "rpe_t", "rpe_r", "scale"}
    assert 0.0 < m["trajectory"]["scale"] < float("inf")
    assert m["train_seconds"] > 0
    assert "pose_refinement" in m["left_out"]


def test_eval_with_test_pose_refinement_reports_both_novel_view_scores(trained):
    scene, run = trained
    assert main(["eval", str(run), "--test-pose-opt", "8"]) == 0
    m = json.loads((run / "metrics.json").read_text())
    opt, plain = m["nvs_pose_opt"], m["nvs"]
    assert opt["steps"] == 8 and opt["num_images"] == plain["num_images"]
    # each view keeps its best pose, its start included: never below the plain score
    assert opt["psnr"] >= plain["psnr"] - 1e-9
    assert opt["mean_rotation_deg"] >= 0.0 and np.isfinite(opt["mean_translation"])
    # moving and static pixels split as for the plain novel views (the scene's test views carry masks)
    assert set(opt) >= {"moving_psnr", "static_psnr", "moving_share"}
    assert opt["moving_share"] == plain["moving_share"] and 0.0 < opt["moving_share"] < 1.0
    assert main(["eval", str(run)]) == 0  # off by default: the key is absent
    assert "nvs_pose_opt" not in json.loads((run / "metrics.json").read_text())
    assert main(["eval", str(run), "--test-pose-opt", "-1"]) == 2  # argparse's refusal, as a status


def test_render_and_export_ply(trained, tmp_path):
    _, run = trained
    png = tmp_path / "r.png"
    assert main(["render", str(run), "--time", "0.5", "--out", str(png)]) == 0
    import cv2
    img = cv2.imread(str(png))
    assert img is not None and img.shape == (24, 40, 3)
    ply = tmp_path / "g.ply"
    assert main(["export-ply", str(run), "--time", "0.25", str(ply)]) == 0
    g = read_ply(ply)
    assert g["means"].shape[1] == 3 and g["means"].shape[0] > 0
    assert np.all(np.isfinite(g["colors"]))


def test_render_with_a_pose_file(trained, tmp_path):
    _, run = trained
    pose = tmp_path / "pose.json"
    T = np.eye(4)
    T[2, 3] = 4.0
    pose.write_text(json.dumps({"cam_T_world": T.tolist()}))
    assert main(["render", str(run), "--time", "0.1", "--pose", str(pose), "--out", str(tmp_path / "p.png")]) == 0
    bad = tmp_path / "bad.json"
    T[0, 0] = 2.0
    bad.write_text(json.dumps({"cam_T_world": T.tolist()}))
    assert main(["render", str(run), "--time", "0.1", "--pose", str(bad), "--out", str(tmp_path / "q.png")]) == 2


def test_errors_exit_2_with_a_message(tmp_path, capsys):
    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "r")]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["make-scene", str(tmp_path / "s"), "--preset", "bogus"]) == 2
    assert "preset" in capsys.readouterr().err
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"train": {"iterz": 3}}))
    assert main(["train", str(tmp_path / "missing"), "--out", str(tmp_path / "r"), "--config", str(cfg)]) == 2
    assert "iterz" in capsys.readouterr().err  # config errors come before the scene is read
    assert main(["eval", str(tmp_path / "norun")]) == 2
    assert not (tmp_path / "r").exists()


def test_help_lists_the_commands(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for cmd in COMMANDS:
        assert cmd in out


COMMANDS = ("demo", "make-scene", "train", "eval", "report", "render", "export-ply")


def _help(argv, capsys):
    assert main(argv) == 0  # main returns the status argparse exits with
    return capsys.readouterr().out


def test_help_names_the_docs_that_explain_each_command(capsys):
    """d2gs --help and every subcommand's --help name a docs/ page that exists, and every docs/
    reference in the help text resolves (file and section)."""
    from test_docs_references import DOCS_REF, docs_index, find_dangling

    index = docs_index()
    for argv in [["--help"]] + [[cmd, "--help"] for cmd in COMMANDS]:
        out = _help(argv, capsys)
        named = {m.group(1) for m in DOCS_REF.finditer(out)}
        assert named, f"d2gs {' '.join(argv)} names no docs/ page:\n{out}"
        assert not find_dangling(out, index), (argv, find_dangling(out, index))
    top = _help(["--help"], capsys)
    for page in ("method.md", "conventions.md", "dataset_format.md", "architecture.md"):
        assert f"docs/{page}" in top
    expected = {"make-scene": "dataset_format.md", "train": "method.md", "eval": "method.md",
                "render": "conventions.md", "export-ply": "method.md", "demo": "method.md", "report": "method.md"}
    for cmd, page in expected.items():
        assert f"docs/{page}" in _help([cmd, "--help"], capsys), cmd


def test_make_scene_writes_a_suite_scene_with_overrides(tmp_path):
    out = tmp_path / "room"
    assert main(["make-scene", str(out), "--preset", "photo_room", "--frames", "3", "--width", "32",
                 "--height", "18", "--exposure", "0", "--rot-noise-deg", "0", "--trans-noise", "0"]) == 0
    cfg = json.loads((out / "suite_config.json").read_text())
    assert (cfg["family"], cfg["exposure_fraction"], cfg["subframes"], cfg["rot_noise_deg"]) == \
        ("photo_room", 0.0, 1, 0.0)
    assert main(["make-scene", str(out), "--preset", "photo_room", "--frames", "3"]) == 2  # exists, no --overwrite


def _report_images(page):
    import base64
    import re

    import cv2
    uris = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    return [cv2.imdecode(np.frombuffer(base64.b64decode(u), np.uint8), cv2.IMREAD_COLOR) for u in uris]


def test_report_is_one_self_contained_html_file(trained, tmp_path):
    _, run = trained
    out = tmp_path / "rep" / "r.html"
    assert main(["report", str(run), "--out", str(out), "--frames", "2"]) == 0
    page = out.read_text()
    assert page.startswith("<!DOCTYPE html>") and page.rstrip().endswith("</html>")
    assert "src=\"http" not in page and "src='http" not in page  # nothing fetched from a server
    images = _report_images(page)
    # 2 frames x (input, render, truth) + their 3 zoomed crops each, the novel views, 2 plots
    assert len(images) >= 2 * 6 + 2 and all(im is not None and im.size > 0 for im in images)
    m = json.loads((run / "metrics.json").read_text())
    assert f"{m['dvs']['psnr']:.2f}" in page and f"{m['input_blur']['psnr']:.2f}" in page
    assert "pose_refinement" in page  # what was left out is said
    for section in ("Metrics", "Error against wall-clock time", "Camera trajectories", "Pictures"):
        assert section in page


def test_report_side_by_side_needs_out_and_names_both_runs(trained, tmp_path, capsys):
    _, run = trained
    assert main(["report", str(run), str(run)]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["report", str(tmp_path / "norun")]) == 2
    assert "norun" in capsys.readouterr().err


def test_zoom_crop_finds_the_detailed_region():
    from d2gs_np.reporting.html import zoom_crop

    img = np.full((40, 60, 3), 0.5)
    rng = np.random.default_rng(0)
    img[24:36, 40:56] = rng.uniform(size=(12, 16, 3))  # the only texture
    crops, (y0, x0, side) = zoom_crop(img, [img, img * 0], fraction=0.25, zoom=3)
    assert side == 10 and crops[0].shape == (30, 30, 3) and not crops[1].any()
    assert 24 - side < y0 <= 36 and 40 - side < x0 <= 56  # the crop overlaps the textured block


def test_demo_quick_writes_the_report_with_the_no_blur_baseline_beside(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out), "--iters", "12"]) == 0
    page = (out / "report.html").read_text()
    assert "deblurred render" in page and "What the numbers say" in page
    run, base = (json.loads((out / d / "metrics.json").read_text()) for d in ("run", "noblur"))
    assert "blur_model" in base["left_out"] and "blur_model" not in run["left_out"]
    assert base["steps"] == run["steps"] == 12  # the same schedule
    said = [line for line in capsys.readouterr().out.splitlines() if "no-blur baseline" in line and "dB" in line]
    assert len(said) == 1 and f"{abs(run['dvs']['psnr'] - base['dvs']['psnr']):.2f} dB" in said[0]
    assert main(["demo", "--quick", "--out", str(out), "--preset", "nope"]) == 2


def test_demo_without_the_baseline_trains_one_run(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out), "--iters", "4", "--no-baseline"]) == 0
    assert (out / "run" / "metrics.json").exists() and not (out / "noblur").exists()


def test_eval_says_how_the_run_compares_with_its_input(trained, capsys):
    scene, run = trained
    assert main(["eval", str(run)]) == 0
    out = capsys.readouterr().out
    m = json.loads((run / "metrics.json").read_text())
    gain = m["dvs"]["psnr"] - m["input_blur"]["psnr"]
    said = [line for line in out.splitlines() if line.startswith("d2gs eval: ")]
    assert len(said) == 2 and (("LOST to its input" in said[0]) == (gain < 0)), said
    assert f"{abs(gain):.2f} dB" in said[0]
    # what is measured without ground truth, always
    assert 0 < m["input_fit"]["psnr"] < 100 and m["input_fit"]["num_images"] == 5
    assert m["sharpness"]["ratio"] == pytest.approx(m["sharpness"]["renders"] / m["sharpness"]["inputs"])
    # the moving and the static pixels apart (the preset's movers: frame masks, and the test views' true masks)
    for key in ("dvs", "input_blur", "nvs"):
        assert 0.0 < m[key]["moving_share"] < 0.5 and np.isfinite(m[key]["moving_psnr"]), key
        assert np.isfinite(m[key]["static_psnr"]), key
    assert (m["dvs"]["moving_psnr"] < m["input_blur"]["moving_psnr"]) == any("moving pixels the method LOST" in s
                                                                            for s in said)
