"""examples/nvs_protocols.py: one row per run, each protocol's figures in its own column."""
import json

import pytest

from example_fixtures import load_example

nvs_protocols = load_example("nvs_protocols.py")


def _columns(line):
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_each_protocol_lands_in_its_column(tmp_path, capsys):
    m = {"dvs": {"psnr": 30.0, "moving_psnr": 25.0, "depth": {"absrel_static": 0.1234}},
         "nvs": {"psnr": 21.0, "moving_psnr": 17.0, "seen_psnr": 22.0},
         "nvs_rig": {"psnr": 24.5, "moving_psnr": 19.5, "seen_psnr": 26.0},
         "trajectory": {"ate": 0.0123}, "steps": 2000}
    run = tmp_path / "cube"
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps(m))
    nvs_protocols.main([str(run), "--labels", "cube noisy"])
    head, _, line = capsys.readouterr().out.strip().splitlines()
    names, cells = _columns(head), _columns(line)
    assert len(names) == len(cells) == 14
    got = dict(zip(names, cells))
    assert got["run"] == "cube noisy"
    assert got["NVS aligned dB"] == "21.00" and got["NVS beside its frame dB"] == "24.50"
    assert got["NVS test poses refined dB"] == "–"  # not evaluated: said, not zero
    assert got["seen px: beside its frame"] == "26.00" and got["static depth AbsRel"] == "0.123"
    assert cells[names.index("NVS beside its frame dB") + 1] == "19.50"  # its moving pixels


def test_a_run_without_metrics_says_to_evaluate(tmp_path):
    with pytest.raises(SystemExit, match="evaluate first"):
        nvs_protocols.main([str(tmp_path)])
    with pytest.raises(SystemExit):
        nvs_protocols.main([str(tmp_path), str(tmp_path), "--labels", "one"])
