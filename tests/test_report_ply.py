"""Error-against-time plots and the PLY layout."""
import numpy as np

from d2gs_np.data.ply import SH_C0, read_ply, write_ply
from d2gs_np.reporting.plots import (comparison_strip, heldout_curve, plot_curves_by_scene, plot_error_vs_time,
                                     plot_loss_terms, read_log)


def _fake_run(path, rows):
    path.mkdir(parents=True)
    lines = ["step,seconds,stage,loss,train_psnr,heldout_psnr,scale,num_gaussians"]
    lines += [f"{s},{t},joint,0.1,{p},{'' if h is None else h},1.0,10" for s, t, p, h in rows]
    (path / "log.csv").write_text("\n".join(lines) + "\n")


def test_plot_error_vs_time_writes_a_png(tmp_path):
    _fake_run(tmp_path / "a", [(0, 0.1, 20.0, 19.0), (10, 1.0, 25.0, None), (20, 2.0, 27.0, 26.0)])
    _fake_run(tmp_path / "b", [(0, 0.2, 18.0, 17.0), (20, 3.0, 24.0, 23.5)])
    out = plot_error_vs_time([tmp_path / "a", tmp_path / "b"], tmp_path / "p.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    c = read_log(tmp_path / "a")
    np.testing.assert_array_equal(c["step"], [0, 10, 20])
    assert np.isnan(c["heldout_psnr"][1]) and c["heldout_psnr"][2] == 26.0


def test_curves_by_scene_draw_a_panel_per_scene_with_the_input_dashed(tmp_path, monkeypatch):
    import matplotlib.figure
    import pytest

    _fake_run(tmp_path / "a", [(0, 0.1, 20.0, 19.0), (10, 1.0, 25.0, None), (20, 2.0, 27.0, 26.0)])
    _fake_run(tmp_path / "b", [(0, 0.2, 18.0, 17.0), (20, 3.0, 24.0, 23.5)])
    t, p = heldout_curve(tmp_path / "a")  # the rows without a held-out value left out
    np.testing.assert_array_equal(t, [0.1, 2.0])
    np.testing.assert_array_equal(p, [19.0, 26.0])
    seen = {}
    save = matplotlib.figure.Figure.savefig

    def spy(fig, *args, **kwargs):  # what each panel holds when the figure is written
        seen["panels"] = [(ax.get_title(), [line.get_linestyle() for line in ax.lines]) for ax in fig.axes]
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)
    rows = [("wall_disk", "geodesic", 0, *heldout_curve(tmp_path / "a"), 24.0),
            ("wall_disk", "noblur", 0, *heldout_curve(tmp_path / "b"), None),
            ("crossing", "geodesic", 1, *heldout_curve(tmp_path / "b"), 21.0)]
    out = plot_curves_by_scene(rows, tmp_path / "figs" / "c.png")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert seen["panels"] == [("wall_disk", ["-", "-", "--"]), ("crossing", ["-", "--"])]
    with pytest.raises(ValueError, match="no cells"):
        plot_curves_by_scene([], tmp_path / "d.png")


def test_plot_loss_terms_needs_term_columns(tmp_path):
    _fake_run(tmp_path / "a", [(0, 0.1, 20.0, 19.0)])
    import pytest

    with pytest.raises(ValueError, match="no loss_<name> columns"):
        plot_loss_terms(tmp_path / "a", tmp_path / "p.png")
    run = tmp_path / "b"
    run.mkdir()
    (run / "log.csv").write_text("step,seconds,stage,loss_photometric,loss_gs\n0,0.1,joint,0.1,0.2\n"
                                 "1,0.2,joint,0.05,\n")
    assert plot_loss_terms(run, tmp_path / "q.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ply_round_trip_in_the_3dgs_layout(tmp_path):
    rng = np.random.default_rng(0)
    n = 7
    g = dict(means=rng.normal(size=(n, 3)), log_scales=rng.normal(size=(n, 3)) - 3,
             quats=rng.normal(size=(n, 4)), opacity_logits=rng.normal(size=n), colors=rng.uniform(size=(n, 3)))
    write_ply(tmp_path / "g.ply", **g)
    raw = (tmp_path / "g.ply").read_bytes()
    header = raw[:raw.index(b"end_header")].decode()
    for prop in ("x", "f_dc_0", "opacity", "scale_2", "rot_0", "rot_3"):
        assert f"property float {prop}\n" in header
    back = read_ply(tmp_path / "g.ply")
    for k, v in g.items():
        np.testing.assert_allclose(back[k], v, rtol=1e-6, atol=1e-6, err_msg=k)  # stored as float32
    # f_dc is the SH DC coefficient viewers expect: rgb = 0.5 + SH_C0 * f_dc.
    f_dc = np.frombuffer(raw[raw.index(b"end_header\n") + 11:], dtype="<f4").reshape(n, 17)[:, 6:9]
    np.testing.assert_allclose(0.5 + SH_C0 * f_dc, g["colors"], atol=1e-6)


def test_comparison_strip_shape():
    a = np.zeros((4, 5, 3))
    s = comparison_strip([[a, a, a], [a, a, a]])
    assert s.shape == (4 * 2 + 2, 5 * 3 + 2 * 2, 3)


def test_mover_crop_frames_the_moving_pixels_with_a_margin():
    from d2gs_np.reporting.html import mover_crop

    mask = np.zeros((40, 60), bool)
    mask[10:18, 50:58] = True  # 8 x 8 near the right border
    img = np.random.default_rng(0).uniform(size=(40, 60, 3))
    crops, (y0, y1, x0, x1) = mover_crop(mask, [img, 1 - img], pad=0.25, zoom=2)
    assert (y0, y1, x0, x1) == (8, 20, 48, 60)  # 2 px each side, clipped at the right border
    assert crops[0].shape == (24, 24, 3) and np.array_equal(crops[0][::2, ::2], img[8:20, 48:60])
    assert np.array_equal(crops[1][::2, ::2], 1 - img[8:20, 48:60])
    assert mover_crop(np.zeros((4, 4), bool), [img]) == (None, None)


def test_depth_pictures_share_the_truths_colour_scale_and_mark_where_there_is_no_surface():
    from d2gs_np.reporting.html import depth_pictures

    true = np.array([[2.0, 4.0, np.inf], [2.0, 4.0, 4.0]])
    depth = np.array([[2.0, 4.0, 3.0], [3.0, 0.0, 4.0]])  # exact, exact, (no truth), +50 %, nothing, exact
    rendered, truth, err = depth_pictures(depth, true)
    assert rendered.shape == truth.shape == err.shape == (2, 3, 3)
    np.testing.assert_array_equal(rendered[0, :2], truth[0, :2])  # the same depth, the same colour
    assert not np.array_equal(truth[0, 0], truth[0, 1])  # near and far differ
    np.testing.assert_array_equal(truth[0, 2], 0.0)  # no surface: black
    np.testing.assert_array_equal(rendered[1, 1], 0.0)  # nothing rendered: black
    np.testing.assert_array_equal(err[0, 0], err[1, 2])  # both exact: the bottom of the error scale
    assert np.sum(err[1, 0]) > np.sum(err[0, 0])  # a 50 % error is brighter (magma rises with the value)
    np.testing.assert_array_equal(err[1, 1], err[1, 0])  # 100 % and 50 % are both at the top (0.5)


def test_the_error_plot_gets_a_depth_panel_when_the_log_has_depth(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    from d2gs_np.reporting import html as report

    run = tmp_path / "a"
    run.mkdir()
    (run / "log.csv").write_text("step,seconds,stage,loss,train_psnr,heldout_psnr,heldout_depth_absrel\n"
                                 "0,0.1,joint,0.1,20,19,0.30\n5,1.0,joint,0.1,22,,\n10,2.0,joint,0.1,25,24,0.12\n")
    made = []
    real = plt.subplots
    monkeypatch.setattr(plt, "subplots", lambda *a, **k: made.append(a) or real(*a, **k))
    assert report._error_vs_time_uri([{"name": "a", "dir": run}]).startswith("data:image/png;base64,")
    assert made[-1][:2] == (1, 2)  # PSNR and depth AbsRel; without the column one panel
    (run / "log.csv").write_text("step,seconds,stage,loss,train_psnr,heldout_psnr\n0,0.1,joint,0.1,20,19\n")
    report._error_vs_time_uri([{"name": "a", "dir": run}])
    assert made[-1][:2] == (1, 1)


def test_the_metrics_table_lists_each_test_views_psnr():
    from d2gs_np.reporting.html import _metrics_table

    views = [{"time": 0.0, "psnr": 22.61}, {"time": 0.35, "psnr": 33.3}, {"time": 1.0, "psnr": None}]
    table = _metrics_table([{"name": "a", "result": {"nvs": {"psnr": 27.9, "views": views}}},
                            {"name": "b", "result": {"nvs": {"psnr": 25.0}}}])
    row = next(r for r in table.split("<tr>") if "each test view" in r)
    assert "0.00: 22.61<br>0.35: 33.30<br>1.00: &ndash;" in row
    assert row.count("&ndash;") == 2  # run b has no per-view figures
