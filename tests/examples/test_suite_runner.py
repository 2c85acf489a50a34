"""examples/suite.py end to end on tiny cells: one table row per scene, a CSV, resume without recompute."""
import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def suite_runner():
    spec = importlib.util.spec_from_file_location("suite_runner", ROOT / "examples" / "suite.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_suite_runner_writes_the_table_and_resumes(tmp_path, suite_runner):
    args = ["--out", str(tmp_path), "--scenes", "wall_disk", "--variants", "sharp", "blur", "noblur",
            "--iters", "3", "--budget", "60", "--size", "0.15", "--threads", "1"]
    assert suite_runner.main(args) == 0
    md = (tmp_path / "suite.md").read_text()
    row = next(line for line in md.splitlines() if line.startswith("| wall_disk"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert all(cells[i] for i in (1, 2, 3, 4, 5)), row  # input, deblurred, no-blur, sharp bound, gain
    csv_rows = (tmp_path / "suite.csv").read_text().splitlines()
    assert len(csv_rows) == 4 and csv_rows[0].startswith("scene,variant")
    assert (tmp_path / "error_vs_time.png").stat().st_size > 0
    # the sharp variant's scene is sharp with true poses; the no-blur run left the blur model out
    sharp = json.loads((tmp_path / "runs" / "wall_disk_s0_sharp" / "metrics.json").read_text())
    noblur = json.loads((tmp_path / "runs" / "wall_disk_s0_noblur" / "metrics.json").read_text())
    assert "blur_model" in sharp["left_out"] and "blur_model" in noblur["left_out"]
    assert sharp["input_blur"]["psnr"] is None or sharp["input_blur"]["psnr"] > 90
    # a second call resumes: finished cells are not recomputed
    stamp = {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/*/metrics.json")}
    assert suite_runner.main(args) == 0
    assert {p: p.stat().st_mtime_ns for p in tmp_path.glob("runs/*/metrics.json")} == stamp


def test_suite_runner_rejects_unknown_scenes(tmp_path, suite_runner):
    with pytest.raises(SystemExit):
        suite_runner.main(["--out", str(tmp_path), "--scenes", "moon_base"])
