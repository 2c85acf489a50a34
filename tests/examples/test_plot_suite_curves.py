"""examples/plot_suite_curves.py: cells are read from their cell.json, log.csv and metrics.json (held-out
rows only), grouped one panel per scene; a folder without cells is refused."""
import json

import numpy as np
import pytest

from example_fixtures import load_example


def _cell(root, scene, variant, rows, input_psnr=None):
    d = root / f"{scene}_s0_{variant}"
    d.mkdir()
    (d / "cell.json").write_text(json.dumps({"scene": scene, "variant": variant, "seed": 0}))
    lines = ["step,seconds,stage,loss,train_psnr,heldout_psnr"]
    lines += [f"{k},{t},joint,0.1,30,{'' if h is None else h}" for k, (t, h) in enumerate(rows)]
    (d / "log.csv").write_text("\n".join(lines) + "\n")
    if input_psnr is not None:
        (d / "metrics.json").write_text(json.dumps({"input_blur": {"psnr": input_psnr}}))


def test_cells_keep_the_held_out_rows_and_the_input_psnr(tmp_path):
    mod = load_example("plot_suite_curves.py")
    _cell(tmp_path, "wall_disk", "geodesic", [(0.0, 20.0), (5.0, None), (10.0, 25.0)], input_psnr=24.0)
    _cell(tmp_path, "wall_disk", "noblur", [(0.0, 19.0), (10.0, 21.0)])
    _cell(tmp_path, "crossing", "geodesic", [(0.0, 18.0), (10.0, 22.0)], input_psnr=21.0)
    (tmp_path / "not_a_cell").mkdir()
    rows = mod.cells(tmp_path)
    assert [(r[0], r[1]) for r in rows] == [("crossing", "geodesic"), ("wall_disk", "geodesic"), ("wall_disk", "noblur")]
    np.testing.assert_array_equal(rows[1][3], [0.0, 10.0])  # the row without a held-out value is left out
    np.testing.assert_array_equal(rows[1][4], [20.0, 25.0])
    assert rows[1][5] == 24.0 and rows[2][5] is None
    out = mod.plot(tmp_path, tmp_path / "c.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_folder_without_cells_is_refused(tmp_path):
    mod = load_example("plot_suite_curves.py")
    with pytest.raises(FileNotFoundError, match="holds no experiment cells"):
        mod.cells(tmp_path)


def test_labelled_folders_share_the_panels(tmp_path):
    mod = load_example("plot_suite_curves.py")
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    _cell(tmp_path / "a", "wall_disk", "geodesic", [(0.0, 20.0), (10.0, 25.0)], input_psnr=24.0)
    _cell(tmp_path / "b", "wall_disk", "geodesic", [(0.0, 20.0), (10.0, 26.0)], input_psnr=24.0)
    rows = mod.cells(tmp_path / "b", "2 threads")
    assert rows[0][1] == "geodesic (2 threads)"
    out = mod.plot([f"1 thread={tmp_path / 'a'}", f"2 threads={tmp_path / 'b'}"], tmp_path / "c.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert mod.cells(tmp_path / "a")[0][1] == "geodesic"  # unlabelled: the variant alone
