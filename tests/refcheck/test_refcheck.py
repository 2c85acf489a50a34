"""The reference-check kit (docs/refcheck.md): export -> compare of our own results passes; a
perturbed, NaN, reshaped or missing result fails and names the case, quantity and index; a
float32 export compares at float32 tolerances; the documented loader runs; the cases are what
they claim; the command line and its errors; gsplat's reference when it is installed.

One float64 export of a few small cases is shared by the module (building the whole default
suite is checked once, by the command-line test).
"""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from d2gs_np import constants as C
from d2gs_np.cli import main
from d2gs_np.refcheck import build_case, compare_dirs, export, format_table, parse_rtol, read_case, run
from d2gs_np.refcheck.cases import DEFAULT_CASES, DEFAULT_CASES_F32
from d2gs_np.refcheck.io import write_results

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["random_small", "tile_border", "near_plane", "many_on_one_pixel", "blur", "deform"]


@pytest.fixture(scope="module")
def golden(tmp_path_factory):
    d = tmp_path_factory.mktemp("rc") / "golden"
    export(d, cases=SMALL, log=None)
    return d


def _copy_results(src, dst):
    """A 'theirs' folder holding exactly our out.* and grad.* (as a port that agrees would)."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in SMALL:
        data = read_case(src / f"{name}.npz")
        write_results(dst, name, data["out"], data["grad"])
    return dst


def _edit(theirs, name, key, fn):
    path = theirs / f"{name}.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays[key] = fn(arrays[key].copy())
    np.savez(path, **arrays)


def _failed(rows):
    return [r for r in rows if not r.ok]


# ---------------------------------------------------------------------------------------------
# export -> compare
# ---------------------------------------------------------------------------------------------


def test_export_compare_of_our_results_passes(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    rows, ok = compare_dirs(golden, theirs)
    assert ok, format_table(rows)
    assert {r.case for r in rows} == set(SMALL)
    assert all(r.max_abs == 0 for r in rows)


def test_reference_renderer_passes_against_the_numba_golden(golden, tmp_path):
    """A genuinely different implementation (our NumPy reference, dense, vectorised) passes at the
    float64 tolerance, and does not agree bit for bit (so the comparison measures something)."""
    run(golden, tmp_path / "ref", renderer="reference", log=None)
    rows, ok = compare_dirs(golden, tmp_path / "ref")
    assert ok, format_table(rows)
    assert max(r.max_rel for r in rows) > 0


def test_one_gradient_entry_off_by_1e_6_relative_fails_naming_it(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    g = read_case(golden / "random_small.npz")["grad"]["means"]
    idx = np.unravel_index(int(np.argmax(np.abs(g))), g.shape)

    def bump(a):
        a[idx] *= 1 + 1e-6
        return a

    _edit(theirs, "random_small", "grad.means", bump)
    rows, ok = compare_dirs(golden, theirs)
    assert not ok
    (bad,) = _failed(rows)
    assert (bad.case, bad.quantity) == ("random_small", "grad.means")
    assert bad.where.startswith(f"gaussian={idx[0]}, comp={idx[1]}")
    assert bad.max_rel == pytest.approx(1e-6, rel=1e-3)
    table = format_table(rows)
    assert f"FAILED random_small grad.means: FAIL gaussian={idx[0]}, comp={idx[1]}" in table


def test_pose_tangent_and_endpoint_gradients_are_checked(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    _edit(theirs, "blur", "grad.xi_end", lambda a: a * (1 + 1e-6))
    nudge = np.array([[0, 0, 0, 0, 0, 1e-6]])
    _edit(theirs, "tile_border", "grad.viewmats_tangent", lambda a: a + nudge * np.abs(a).max())
    rows, _ = compare_dirs(golden, theirs)
    assert {(r.case, r.quantity) for r in _failed(rows)} == {("blur", "grad.xi_end"),
                                                            ("tile_border", "grad.viewmats_tangent")}
    tangent = next(r for r in rows if r.quantity == "grad.viewmats_tangent" and r.case == "tile_border")
    assert tangent.where.startswith("cam=0, comp=5")


def test_nan_fails_naming_its_index(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")

    def nan_at(a):
        a[0, 3, 5, 1] = np.nan
        return a

    _edit(theirs, "near_plane", "out.image", nan_at)
    rows, ok = compare_dirs(golden, theirs)
    (bad,) = _failed(rows)
    assert not ok and bad.quantity == "out.image" and bad.where == "cam=0, row=3, col=5, ch=1"
    assert "non-finite" in bad.note


def test_missing_case_quantity_and_wrong_shape_are_reported(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    (theirs / "deform.npz").unlink()
    path = theirs / "tile_border.npz"
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != "grad.backgrounds"}
    arrays["out.depths"] = arrays["out.depths"][0]  # (N,) instead of (1, N)
    np.savez(path, **arrays)
    rows, ok = compare_dirs(golden, theirs)
    assert not ok
    bad = {(r.case, r.quantity): r for r in _failed(rows)}
    assert set(bad) == {("deform", "*"), ("tile_border", "grad.backgrounds"), ("tile_border", "out.depths")}
    assert bad[("deform", "*")].status == "MISSING" and "deform.npz" in bad[("deform", "*")].note
    assert bad[("tile_border", "grad.backgrounds")].status == "MISSING"
    assert "shape (8,), expected (1, 8)" in bad[("tile_border", "out.depths")].note


def test_radii_compare_exactly_in_float64(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    _edit(theirs, "random_small", "out.radii", lambda a: a + (np.arange(a.size).reshape(a.shape) == 3))
    rows, _ = compare_dirs(golden, theirs)
    (bad,) = _failed(rows)
    assert bad.quantity == "out.radii" and bad.where.startswith("cam=0, gaussian=1, axis=1")


def test_rtol_overrides(golden, tmp_path):
    theirs = _copy_results(golden, tmp_path / "theirs")
    _edit(theirs, "random_small", "grad.means", lambda a: a * (1 + 1e-6))
    assert not compare_dirs(golden, theirs)[1]
    assert compare_dirs(golden, theirs, rtol=parse_rtol(["grad.means=1e-5"]))[1]
    assert compare_dirs(golden, theirs, rtol=parse_rtol(["1e-5"]))[1]
    assert not compare_dirs(golden, theirs, rtol=parse_rtol(["1e-5", "grad.means=1e-7"]))[1]
    for bad in (["means=1e-3"], ["grad.means=x"], ["-1"]):
        with pytest.raises(ValueError, match="--rtol"):
            parse_rtol(bad)


# ---------------------------------------------------------------------------------------------
# float32
# ---------------------------------------------------------------------------------------------


def test_float32_export_compares_at_float32_tolerances(tmp_path):
    """Our float32 Numba path on a float32 export passes the float32 defaults and fails the
    float64 ones (its errors are float32 rounding, ~1e-7..1e-5 of scale)."""
    gold = tmp_path / "g32"
    export(gold, cases=["random_medium", "opacity_extremes", "blur", "deform"], dtype="float32", log=None)
    index = json.loads((gold / "cases.json").read_text())
    assert index["dtype"] == "float32" and index["golden_dtype"] == "float64"
    data = read_case(gold / "random_medium.npz")
    assert data["in"]["means"].dtype == np.float32 and data["cot"]["image"].dtype == np.float32
    assert data["out"]["image"].dtype == np.float64  # golden: float64 from the float32 inputs
    run(gold, tmp_path / "ours32", log=None)  # default: the export's dtype
    rows, ok = compare_dirs(gold, tmp_path / "ours32")
    assert ok, format_table(rows)
    assert {r.tol for r in rows if r.quantity.startswith("grad.")} == {C.REFCHECK_RTOL_F32_GRAD}
    worst = max(r.max_rel for r in rows if r.quantity != "out.radii")
    assert 1e-8 < worst < C.REFCHECK_RTOL_F32_OUTPUT
    rows64, ok64 = compare_dirs(gold, tmp_path / "ours32", tolerances="float64")
    assert not ok64


def test_float32_default_suite_leaves_out_the_float64_only_case():
    assert "extreme_anisotropy" in DEFAULT_CASES and "extreme_anisotropy" not in DEFAULT_CASES_F32
    assert set(DEFAULT_CASES) - set(DEFAULT_CASES_F32) == {"extreme_anisotropy"}


# ---------------------------------------------------------------------------------------------
# the cases and the file format
# ---------------------------------------------------------------------------------------------


def test_cases_json_describes_every_array(golden):
    index = json.loads((golden / "cases.json").read_text())
    assert index["format"] == "d2gs_np-refcheck" and index["version"] == 1
    for entry in index["cases"]:
        data = read_case(golden / entry["file"])
        for sec, key in (("in", "inputs"), ("cot", "cotangents"), ("out", "outputs"), ("grad", "gradients")):
            assert set(entry[key]) == set(data[sec]), (entry["name"], sec)
            for name, desc in entry[key].items():
                assert tuple(desc["shape"]) == data[sec][name].shape
                assert desc["dtype"] == str(data[sec][name].dtype)


def test_render_layout_is_gsplats(golden):
    data = read_case(golden / "tile_border.npz")
    inp, out, grad = data["in"], data["out"], data["grad"]
    n, H, W = inp["means"].shape[0], int(inp["height"]), int(inp["width"])
    assert inp["viewmats"].shape == (1, 4, 4) and inp["Ks"].shape == (1, 3, 3) and inp["backgrounds"].shape == (1, 3)
    assert out["image"].shape == (1, H, W, 3) and out["alpha"].shape == (1, H, W, 1)
    assert out["radii"].shape == (1, n, 2) and out["radii"].dtype == np.int32
    assert np.all(grad["viewmats"][0, 3] == 0)  # bottom row: no gradient
    # every gradient is that of L = sum <cot.y, out.y>: the background enters as T_final * bg
    T = 1 - out["alpha"][0, ..., 0]
    np.testing.assert_allclose(grad["backgrounds"][0], np.einsum("hw,hwc->c", T, data["cot"]["image"][0]), rtol=1e-12)


def test_pose_tangent_is_the_left_perturbation_derivative(golden):
    """grad.viewmats_tangent[i] = dL/d delta_i for viewmat <- exp(delta) viewmat: the directional
    derivative of L along exp(h e_i), from the entrywise gradient (first order in h)."""
    from d2gs_np.geometry.se3 import se3_exp

    data = read_case(golden / "random_small.npz")
    T, G = data["in"]["viewmats"][0], data["grad"]["viewmats"][0]
    for i in range(6):
        e = np.zeros(6)
        e[i] = 1e-7
        dT = (se3_exp(e) @ T - se3_exp(-e) @ T) / 2e-7  # d/dh exp(h e_i) T
        assert np.sum(G * dT) == pytest.approx(data["grad"]["viewmats_tangent"][0, i], rel=1e-6, abs=1e-9)


def test_many_on_one_pixel_stops_after_916(golden):
    data = read_case(golden / "many_on_one_pixel.npz")
    used = np.any(data["grad"]["colors"] != 0, axis=1)
    assert data["in"]["means"].shape[0] == 100_000 and np.count_nonzero(used) == 916
    np.testing.assert_allclose(1 - data["out"]["alpha"][0, 0, 0, 0], 0.99**916, rtol=1e-12)


def test_opacity_cutoff_case_composites_only_above_the_cutoff():
    """Gaussians 0 and 2 (opacity above 1/255) are composited on their centre pixel only, with
    alpha = opacity (sigma = 0 there) and T = 1 (nearest); 1 and 3 (below) nowhere."""
    from d2gs_np.refcheck import compute

    case = build_case("opacity_cutoff")
    _, grads = compute(case.kind, case.inputs, case.cotangents)
    used = np.any(grads["colors"] != 0, axis=1)
    np.testing.assert_array_equal(used, [True, False, True, False, True])
    o = case.inputs["opacities"]
    np.testing.assert_allclose(grads["colors"][0], o[0] * case.cotangents["image"][0, 3, 3], rtol=1e-14)
    assert case.margins["view0"]["alpha_threshold"] == pytest.approx(1e-3, rel=1e-6)


def test_blur_case_virtual_poses_run_from_start_to_end(golden):
    from d2gs_np.geometry.se3 import se3_exp

    data = read_case(golden / "blur.npz")
    T_hat = data["in"]["viewmats"][0]
    poses = data["out"]["viewmats_virtual"]
    assert poses.shape == (int(data["in"]["num_virtual"]), 4, 4)
    np.testing.assert_allclose(poses[0], se3_exp(data["in"]["xi_start"]) @ T_hat, atol=1e-12)
    np.testing.assert_allclose(poses[-1], se3_exp(data["in"]["xi_end"]) @ T_hat, atol=1e-12)
    assert np.all(np.abs(data["grad"]["xi_start"]) > 0) and np.all(np.abs(data["grad"]["xi_end"]) > 0)


def test_margins_of_the_random_cases():
    case = build_case("random_small")
    assert min(case.margins["view0"].values()) >= 1e-4


def test_unknown_case_and_dtype_raise_before_work(tmp_path):
    with pytest.raises(ValueError, match="unknown refcheck case 'nope'.*random_small"):
        export(tmp_path / "x", cases=["random_small", "nope"], log=None)
    assert not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="dtype must be 'float64' or 'float32'"):
        export(tmp_path / "y", dtype="float16", log=None)
    with pytest.raises(FileNotFoundError, match="not a refcheck export"):
        compare_dirs(tmp_path, tmp_path)


# ---------------------------------------------------------------------------------------------
# the documented loader
# ---------------------------------------------------------------------------------------------


def test_loader_example_in_the_docs_runs(golden):
    text = (ROOT / "docs" / "refcheck.md").read_text()
    section = text.split("## 8. Loading a case in plain NumPy", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert len(code.strip().splitlines()) <= 14
    ns = {"folder": str(golden)}
    where = "docs/refcheck.md §8"
    exec(compile(code, where, "exec"), ns)
    first = json.loads((golden / "cases.json").read_text())["cases"][0]["name"]
    ref = read_case(golden / f"{first}.npz")
    for sec in ("in", "cot", "out", "grad"):
        assert set(ns["case"][sec]) == set(ref[sec])
        for k in ref[sec]:
            np.testing.assert_array_equal(ns["case"][sec][k], ref[sec][k])


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------


def test_cli_export_compare_and_exit_codes(tmp_path, capsys):
    gold = tmp_path / "gold"
    assert main(["refcheck", "export", str(gold)]) == 0  # the whole default suite
    names = [e["name"] for e in json.loads((gold / "cases.json").read_text())["cases"]]
    assert names == list(DEFAULT_CASES)
    assert main(["refcheck", "compare", str(gold), str(gold)]) == 0
    out = capsys.readouterr().out
    assert re.search(rf"(\d+) quantities in {len(DEFAULT_CASES)} cases: \1 passed, 0 failed", out)
    theirs = tmp_path / "theirs"
    shutil.copytree(gold, theirs)
    _edit(theirs, "deform", "grad.t", lambda a: a * (1 + 1e-6))
    assert main(["refcheck", "compare", str(gold), str(theirs)]) == 1
    captured = capsys.readouterr()
    assert "FAILED deform grad.t: FAIL (scalar)" in captured.out and "differ beyond" in captured.err
    assert main(["refcheck", "compare", str(gold), str(theirs), "--rtol", "grad.t=1e-5"]) == 0
    assert main(["refcheck", "compare", str(gold), str(tmp_path / "none")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["refcheck", "export", str(tmp_path / "z"), "--cases", "bogus"]) == 2


def test_cli_help_names_the_docs_page(capsys):
    assert main(["refcheck", "--help"]) == 0
    assert "docs/refcheck.md" in capsys.readouterr().out
    for action in ("export", "compare", "run", "gsplat"):
        assert main(["refcheck", action, "--help"]) == 0
        assert "docs/refcheck.md" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------
# gsplat's reference (optional)
# ---------------------------------------------------------------------------------------------


def _gsplat_or_skip():
    from d2gs_np.refcheck.gsplat_runner import gsplat_status

    ok, why = gsplat_status()
    if not ok:
        pytest.skip(f"gsplat's reference is not available: {why}")


def test_gsplat_reference_matches(golden, tmp_path):
    _gsplat_or_skip()
    from d2gs_np.refcheck.gsplat_runner import run_gsplat

    done = run_gsplat(golden, tmp_path / "gsplat", cases=["random_small", "tile_border", "near_plane", "blur",
                                                          "deform"], log=None)
    assert done == ["random_small", "tile_border", "near_plane", "blur"]  # no gsplat deformation
    rows, ok = compare_dirs(golden, tmp_path / "gsplat", cases=done)
    assert ok, format_table(rows)


def test_gsplat_unavailable_is_a_clear_error(golden, monkeypatch, capsys):
    """Without torch the command stops before any work with the reason and the install line."""
    import builtins

    real_import = builtins.__import__

    def no_torch(name, *args, **kwargs):
        if name == "torch" or name.startswith("torch."):
            raise ImportError("No module named 'torch'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_torch)
    assert main(["refcheck", "gsplat", str(golden), "--out", str(golden.parent / "gs_none")]) == 2
    err = capsys.readouterr().err
    assert "torch cannot be imported" in err and "pip install" in err
    assert not (golden.parent / "gs_none").exists()
