"""examples/suite.py end to end on tiny cells: one table row per scene, a CSV, resume without recompute."""
import json

import pytest

from example_fixtures import load_example


def _no_stretch(tmp_path):
    """A config that ends each cell with its 3-step schedule: a budgeted run otherwise trains on to
    spend its budget (TrainConfig.stretch_to_budget), a minute per cell that tests nothing here."""
    path = tmp_path / "no_stretch.json"
    path.write_text(json.dumps({"train": {"stretch_to_budget": False}}))
    return ["--config", str(path)]


def _cell(out, experiment, variant):
    from d2gs_np.experiments.sweep import EXPERIMENTS, cell_folder

    v = next(v for v in EXPERIMENTS[experiment] if v.name == variant)
    return cell_folder(out, experiment, "wall_disk", v, 0, 0.15)


@pytest.fixture(scope="module")
def suite_runner():
    return load_example("suite.py", "suite_runner")


@pytest.mark.slow
def test_suite_runner_writes_the_table_and_resumes(tmp_path, suite_runner):
    args = ["--out", str(tmp_path / "out"), "--scenes", "wall_disk", "--variants", "sharp", "blur", "noblur",
            "--iters", "3", "--budget", "60", "--size", "0.15", "--threads", "1", *_no_stretch(tmp_path)]
    tmp_path = tmp_path / "out"
    assert suite_runner.main(args) == 0
    md = (tmp_path / "suite_by_scene.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| wall_disk"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert all(cells[i] for i in (1, 2, 3, 4, 5)), row  # input, deblurred, no-blur, sharp bound, gain
    csv_rows = (tmp_path / "suite.csv").read_text().splitlines()
    assert len(csv_rows) == 4 and csv_rows[0].startswith("scene,seed,variant")
    assert (tmp_path / "suite_error_vs_time.png").stat().st_size > 0
    # the sharp variant's scene is sharp with true poses; the no-blur run left the blur model out
    sharp = json.loads((_cell(tmp_path, "suite", "sharp") / "metrics.json").read_text())
    noblur = json.loads((_cell(tmp_path, "suite", "noblur") / "metrics.json").read_text())
    assert "blur_model" in sharp["left_out"] and "blur_model" in noblur["left_out"]
    assert sharp["input_blur"]["psnr"] is None or sharp["input_blur"]["psnr"] > 90
    # a second call resumes: finished cells are not recomputed
    stamp = {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/*/*/metrics.json")}
    assert len(stamp) == 3
    assert suite_runner.main(args) == 0
    assert {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/*/*/metrics.json")} == stamp


def test_suite_runner_rejects_unknown_scenes(tmp_path, suite_runner):
    with pytest.raises(SystemExit):
        suite_runner.main(["--out", str(tmp_path), "--scenes", "moon_base"])


def test_ablation_variants_turn_on_one_regulariser_each(suite_runner, tmp_path):
    from d2gs_np.experiments.sweep import EXPERIMENTS, scene_folder, variant_config
    from d2gs_np.train.config import METHOD_REGULARISER_WEIGHTS

    def weights(name):
        v = next(v for v in EXPERIMENTS["suite-ablation"] + EXPERIMENTS["suite"] if v.name == name)
        loss = variant_config(v).loss
        return {k: getattr(loss, k) for k in METHOD_REGULARISER_WEIGHTS}

    assert suite_runner.ABLATION == ("render_only", "+ts", "+gs", "+freq", "+reproj", "all")
    assert weights("render_only") == {k: 0.0 for k in METHOD_REGULARISER_WEIGHTS}
    assert weights("+gs") == {"lambda_ts": 0.0, "lambda_gs": 0.01, "lambda_freq": 0.0, "lambda_reproj": 0.0}
    assert weights("all") == METHOD_REGULARISER_WEIGHTS
    # every ablation variant trains on the blur variant's scene (blurry input, true poses)
    blur = next(v for v in EXPERIMENTS["suite"] if v.name == "blur")
    assert {scene_folder(tmp_path, "wall_disk", v, 0) for v in EXPERIMENTS["suite-ablation"]} == \
        {scene_folder(tmp_path, "wall_disk", blur, 0)}


@pytest.mark.slow
def test_ablation_writes_its_table(tmp_path, suite_runner):
    args = ["--out", str(tmp_path / "out"), "--scenes", "wall_disk", "--variants", "render_only", "all",
            "--iters", "3", "--budget", "60", "--size", "0.15", "--threads", "1", *_no_stretch(tmp_path)]
    tmp_path = tmp_path / "out"
    assert suite_runner.main(args) == 0
    md = (tmp_path / "ablation_by_scene.md").read_text()
    rows = [line for line in md.splitlines() if line.startswith("| wall_disk")]
    assert [r.split("|")[2].strip() for r in rows] == ["render_only", "all"]
    assert all(r.split("|")[3].strip() for r in rows), rows  # DVS PSNR present
    all_run = json.loads((_cell(tmp_path, "suite-ablation", "all") / "metrics.json").read_text())
    only = json.loads((_cell(tmp_path, "suite-ablation", "render_only") / "metrics.json").read_text())
    assert not {"loss_ts", "loss_gs", "loss_freq"} & set(all_run["left_out"])
    assert {"loss_ts", "loss_gs", "loss_freq"} <= set(only["left_out"])
    assert all_run["num_gaussians"] > 0
