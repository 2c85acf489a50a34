"""examples/plot_pose_runs.py: reads run logs, writes the figure, and refuses a bad argument."""
import json

import pytest

from example_fixtures import load_example


def _module():
    return load_example("plot_pose_runs.py")


def _run(tmp_path, name, with_solver):
    d = tmp_path / name
    d.mkdir()
    lines = ["step,seconds,heldout_psnr"] + [f"{s},{s * 0.5:.1f},{20 + s / 100:.2f}" for s in range(0, 400, 50)]
    (d / "log.csv").write_text("\n".join(lines) + "\n")
    if with_solver:
        calls = [{"step": 150, "ate_before": 0.02, "ate_after": 0.01}, {"step": 300, "ate_before": 0.01, "ate_after": 0.008}]
        (d / "pose_solver.json").write_text(json.dumps(calls))
    return d


def test_writes_the_figure_and_reads_the_curves(tmp_path):
    mod = _module()
    a, b = _run(tmp_path, "a", True), _run(tmp_path, "b", False)
    t, ate = mod._ate_curve(a)
    assert t == [0.0, 75.0, 150.0] and ate == [0.02, 0.01, 0.008]
    assert mod._ate_curve(b) is None
    assert mod._heldout(b)[1][0] == 20.0
    out = tmp_path / "fig.png"
    mod.main([f"x={a}", f"y={b}", "--given-ate", "0.05", "--out", str(out)])
    assert out.stat().st_size > 1000


def test_refuses_a_run_without_a_log(tmp_path):
    with pytest.raises(SystemExit):
        _module().main([f"x={tmp_path}", "--out", str(tmp_path / "f.png")])
    with pytest.raises(SystemExit):
        _module().main(["no-equals-sign", "--out", str(tmp_path / "f.png")])


def test_a_run_without_a_solver_or_a_given_ate_gets_the_psnr_panel_alone(tmp_path):
    """No trajectory to draw: one panel, half the width of the two-panel figure (5.5 in a panel)."""
    import matplotlib.image

    mod = _module()
    a, b = _run(tmp_path, "a", True), _run(tmp_path, "b", False)
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    mod.main([f"y={b}", "--out", str(one)])
    mod.main([f"x={a}", f"y={b}", "--out", str(two)])
    w1, w2 = matplotlib.image.imread(one).shape[1], matplotlib.image.imread(two).shape[1]
    assert w2 == 2 * w1, (w1, w2)
