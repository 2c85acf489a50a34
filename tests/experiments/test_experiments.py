"""Experiments: every variant is a valid config, a sweep runs on a two-worker LocalCluster and on the
local process pool, failed cells are retried and reported, finished cells are never recomputed."""
import json

import pytest

from d2gs_np.experiments import sweep as ex

TINY = dict(size=40 / 240, frames=4, iters=3, threads=1)


def test_every_variant_of_every_experiment_is_a_valid_config():
    for name, variants in ex.EXPERIMENTS.items():
        assert len({v.name for v in variants}) == len(variants), name
        for v in variants:
            cfg = ex.variant_config(v, iters=7)
            assert cfg.train.iters == 7
    vv = {v.name: ex.variant_config(v) for v in ex.EXPERIMENTS["virtual-views"]}
    assert vv["n16"].blur.num_virtual == 16 and vv["n1"].train.blur == "off"
    base = {v.name: ex.variant_config(v) for v in ex.EXPERIMENTS["baselines"]}
    # the no-blur and two-stage rows are the paper's GaussianFlow-like rows: no blur model, no pose solver
    for name in ("noblur", "two_stage"):
        assert (base[name].train.blur, base[name].pose_solver.mode) == ("off", "off")
    assert (base["full"].train.blur, base["full"].pose_solver.mode) == ("auto", "auto")
    prog = {v.name: ex.variant_config(v) for v in ex.EXPERIMENTS["progressive"]}
    assert not prog["none"].train.progressive and prog["linear"].schedule.kind == "linear"
    abl = {v.name: ex.variant_config(v) for v in ex.EXPERIMENTS["ablation"]}
    assert (abl["render_only"].loss.lambda_ts, abl["render_only"].loss.lambda_gs, abl["render_only"].loss.lambda_freq,
            abl["render_only"].pose_solver.mode) == (0.0, 0.0, 0.0, "off")
    assert abl["+gs"].loss.lambda_gs > 0 and abl["+gs"].loss.lambda_ts == 0 and abl["+gs"].pose_solver.mode == "off"
    assert abl["+reproj"].pose_solver.mode == "on" and abl["all"].loss.lambda_ts > 0
    with pytest.raises(ValueError, match="bogus"):
        ex.variant_config(ex.Variant("x", config={"train": {"bogus": 1}}))


def test_bad_requests_fail_before_any_cell(tmp_path):
    with pytest.raises(ValueError, match="unknown experiment"):
        ex.run_experiment("nope", tmp_path, ["dynamic"], iters=2)
    with pytest.raises(ValueError, match="unknown scene"):
        ex.run_experiment("baselines", tmp_path, ["atlantis"], iters=2)
    with pytest.raises(ValueError, match="no variant"):
        ex.run_experiment("baselines", tmp_path, ["dynamic"], iters=2, variants=["full", "magic"])
    with pytest.raises(ValueError, match="budget"):
        ex.run_experiment("baselines", tmp_path, ["dynamic"])
    assert not (tmp_path / "runs").exists()


def test_default_threads_spend_the_machine():
    assert ex.default_threads(1, cores=2) == 2  # one cell at a time gets both cores
    assert ex.default_threads(2, cores=2) == 1
    assert ex.default_threads(3, cores=8) == 2  # the floor: never more threads than cores
    assert ex.default_threads(4, cores=2) == 1  # never fewer than one


def test_a_sweep_without_threads_gives_each_cell_cores_over_jobs(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(ex, "_run_cells", lambda cells, out, retries, kw, jobs, scheduler: seen.append(kw) or [])
    monkeypatch.setattr(ex, "write_outputs", lambda *a, **k: None)
    monkeypatch.setattr(ex.os, "cpu_count", lambda: 6)
    ex.run_experiment("baselines", tmp_path, ["dynamic"], iters=2, variants=["full"], jobs=2)
    ex.run_experiment("baselines", tmp_path, ["dynamic"], iters=2, variants=["full"], jobs=2, threads=1)
    assert [kw["threads"] for kw in seen] == [3, 1]


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as c:
        with distributed.Client(c) as client:
            yield client


def test_a_sweep_on_a_two_worker_cluster_retries_reports_and_resumes(tmp_path, cluster, monkeypatch):
    calls = []
    real = ex.run_cell

    def flaky(out, scene, variant, seed, **kw):
        calls.append(variant.name)
        if variant.name == "n2" and calls.count("n2") == 1:
            raise RuntimeError("transient failure")  # the retry succeeds
        if variant.name == "n4":
            raise RuntimeError("always fails")
        return real(out, scene, variant, seed, **kw)

    monkeypatch.setattr(ex, "run_cell", flaky)  # workers are threads of this process (processes=False)
    recs = ex.run_experiment("virtual-views", tmp_path, ["dynamic"], [0], variants=["n1", "n2", "n4"],
                             scheduler=cluster, retries=1, **TINY)
    by = {r["variant"]: r for r in recs}
    assert [r["variant"] for r in recs] == ["n1", "n2", "n4"]  # in the experiment's order
    assert by["n1"]["status"] == "ok" and by["n1"]["attempts"] == 1, by["n1"].get("traceback")
    assert by["n2"]["status"] == "ok" and by["n2"]["attempts"] == 2
    assert by["n4"]["status"] == "failed" and "always fails" in by["n4"]["error"] and by["n4"]["attempts"] == 2
    assert by["n1"]["steps"] == 3 and by["n1"]["dvs_psnr"] is not None
    md = (tmp_path / "virtual-views.md").read_text()
    assert "FAILED" in md and "always fails" in md
    assert (tmp_path / "virtual-views.csv").read_text().count("\n") == 4
    assert (tmp_path / "virtual-views_error_vs_time.png").exists()
    # resume: finished cells are not recomputed (their metrics files are untouched)
    m1 = ex.cell_folder(tmp_path, "virtual-views", "dynamic", ex.EXPERIMENTS["virtual-views"][0], 0, TINY["size"],
                        TINY["frames"]) / "metrics.json"
    stamp = m1.stat().st_mtime_ns
    monkeypatch.setattr(ex, "run_cell", real)
    again = ex.run_experiment("virtual-views", tmp_path, ["dynamic"], [0], variants=["n1", "n2"], scheduler=cluster,
                              **TINY)
    assert all(r["status"] == "ok" for r in again) and m1.stat().st_mtime_ns == stamp
    assert json.loads(m1.read_text())["steps"] == 3


def test_baselines_on_the_local_process_pool(tmp_path):
    recs = ex.run_experiment("baselines", tmp_path, ["dynamic"], [0], jobs=2, **TINY)
    by = {r["variant"]: r for r in recs}
    assert set(by) == {"full", "noblur", "two_stage", "sharp_bound"}
    assert all(r["status"] == "ok" for r in recs), [r.get("traceback") for r in recs]
    cell = {v.name: ex.cell_folder(tmp_path, "baselines", "dynamic", v, 0, TINY["size"], TINY["frames"])
            for v in ex.EXPERIMENTS["baselines"]}
    two = json.loads((cell["two_stage"] / "metrics.json").read_text())
    assert "blur_model" in two["left_out"]  # the deconvolved frames are trained as sharp input
    sharp = json.loads((cell["sharp_bound"] / "metrics.json").read_text())
    assert sharp["input_blur"]["psnr"] is None or sharp["input_blur"].get("identical") or \
        sharp["input_blur"]["psnr"] > by["full"]["input_psnr"]  # sharp inputs: far closer to the truth
    # FLIP agrees: the sharp inputs are perceptually nearer the truth than the blurry ones
    assert sharp["input_blur"]["flip"] < by["full"]["input_flip"]


def test_the_local_pool_runs_as_many_cells_at_once_as_jobs():
    """Four cells on two local workers: both workers run cells (with Dask's default batching of
    ready tasks, all four went to one worker's job while the other stood idle)."""
    import os

    import dask

    def cell(i):
        import time

        time.sleep(0.5)
        return os.getpid()

    pids = ex.compute_local([dask.delayed(cell, pure=False)(i) for i in range(4)], jobs=2)
    assert len(pids) == 4 and len(set(pids)) == 2 and os.getpid() not in pids


def test_a_finished_cell_is_never_answered_for_other_settings(tmp_path):
    """The same OUT swept again with another budget (or steps) is refused, naming the cell and
    what differs; variants of two experiments that share a name (``noblur``) get their own
    folders, so one never resumes the other's result."""
    kw = dict(TINY)
    recs = ex.run_experiment("virtual-views", tmp_path, ["dynamic"], [0], variants=["n1"], **kw)
    assert recs[0]["status"] == "ok", recs[0].get("traceback")
    kw["iters"] = 4
    again = ex.run_experiment("virtual-views", tmp_path, ["dynamic"], [0], variants=["n1"], retries=0, **kw)
    assert again[0]["status"] == "failed" and "other settings" in again[0]["error"] and "iters" in again[0]["error"]
    # with a time budget the thread count decides the steps bought, so it is a setting too; with
    # steps alone it is not (results do not depend on it)
    v = ex.EXPERIMENTS["virtual-views"][0]
    s1 = ex.cell_settings("e", "dynamic", v, 0, 60.0, None, 1.0, None, None, threads=1)
    assert s1 != ex.cell_settings("e", "dynamic", v, 0, 60.0, None, 1.0, None, None, threads=2)
    assert ex.cell_settings("e", "dynamic", v, 0, None, 5, 1.0, None, None, threads=1) == \
        ex.cell_settings("e", "dynamic", v, 0, None, 5, 1.0, None, None, threads=2)
    a = ex.cell_folder(tmp_path, "baselines", "dynamic", ex.EXPERIMENTS["baselines"][1], 0)
    b = ex.cell_folder(tmp_path, "suite", "dynamic", ex.EXPERIMENTS["suite"][2], 0)
    assert ex.EXPERIMENTS["baselines"][1].name == ex.EXPERIMENTS["suite"][2].name == "noblur" and a != b


def test_scenes_of_other_sizes_or_frame_counts_never_share_a_folder_or_a_marker(tmp_path):
    """Sizes with a decimal point (x0.6667, x0.5) once shared one ".done" marker (with_suffix cut
    the name at the dot), and the frame count was not in the name: a second sweep in the same OUT
    reused the first one's scene. Each setting now makes its own scene."""
    from d2gs_np.data.io import load_scene

    v = ex.EXPERIMENTS["virtual-views"][0]
    a = ex._make_scene(tmp_path, "dynamic", v, 0, 40 / 240, 4)
    b = ex._make_scene(tmp_path, "dynamic", v, 0, 48 / 240, 4)
    c = ex._make_scene(tmp_path, "dynamic", v, 0, 40 / 240, 5)
    assert len({a, b, c}) == 3
    assert len({ex.scene_done_marker(f) for f in (a, b, c)}) == 3
    assert all(ex.scene_done_marker(f).exists() for f in (a, b, c))
    sa, sb, sc = load_scene(a), load_scene(b), load_scene(c)
    assert (sa.frames[0].width, sa.num_frames) == (40, 4)
    assert (sb.frames[0].width, sb.num_frames) == (48, 4)
    assert (sc.frames[0].width, sc.num_frames) == (40, 5)


def test_cells_sharing_a_scene_never_read_it_half_written(tmp_path):
    """Four threads make the same scene at once (as cells of one sweep do) and each loads it at
    once: every load sees a whole scene, one folder is published, no private copy is left."""
    import threading

    from d2gs_np.data.io import load_scene

    v = ex.EXPERIMENTS["virtual-views"][0]
    barrier, errors, folders = threading.Barrier(4), [], []

    def cell():
        try:
            barrier.wait()
            f = ex._make_scene(tmp_path, "dynamic", v, 0, TINY["size"], TINY["frames"])
            folders.append(f)
            sc = load_scene(f)
            assert sc.num_frames == TINY["frames"]
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))

    threads = [threading.Thread(target=cell) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert len(set(folders)) == 1 and ex.scene_done_marker(folders[0]).exists()
    assert not [p.name for p in folders[0].parent.iterdir() if ".tmp-" in p.name]


def test_the_table_shows_the_moving_and_the_static_pixels_apart():
    from d2gs_np.experiments.sweep import flatten, table

    metrics = {"dvs": {"psnr": 27.0, "moving_psnr": 21.25, "static_psnr": 28.5},
               "input_blur": {"psnr": 26.0, "moving_psnr": 22.75, "static_psnr": 26.5}, "nvs": {"moving_psnr": 18.0}}
    row = flatten(metrics)
    assert (row["dvs_moving_psnr"], row["input_static_psnr"], row["nvs_moving_psnr"]) == (21.25, 26.5, 18.0)
    line = table([dict(scene="s", seed=0, variant="v", status="ok", **row)]).splitlines()[2]
    assert "22.75 -> 21.25" in line and "26.50 -> 28.50" in line


def test_the_table_shows_both_novel_view_protocols():
    from d2gs_np.experiments.sweep import flatten, table

    metrics = {"nvs": {"psnr": 21.5}, "nvs_rig": {"psnr": 24.25, "moving_psnr": 19.5}}
    row = flatten(metrics)
    assert (row["nvs_psnr"], row["nvs_rig_psnr"], row["nvs_rig_moving_psnr"]) == (21.5, 24.25, 19.5)
    head, _, line = table([dict(scene="s", seed=0, variant="v", status="ok", **row)]).splitlines()
    cells = [c.strip() for c in line.split("|")]
    names = [c.strip() for c in head.split("|")]
    assert len(cells) == len(names)
    assert cells[names.index("NVS PSNR dB")] == "21.50"
    assert cells[names.index("NVS beside its frame dB")] == "24.25"


def test_the_table_shows_the_seen_pixels_and_the_static_depth_error():
    from d2gs_np.experiments.sweep import flatten, table

    metrics = {"nvs": {"psnr": 21.5, "seen_psnr": 23.75, "depth": {"absrel_static": 0.125}},
               "dvs": {"depth": {"absrel_static": 0.0625, "absrel_moving": 0.5}}}
    row = flatten(metrics)
    assert (row["nvs_seen_psnr"], row["dvs_depth_absrel_static"], row["nvs_depth_absrel_static"]) == (23.75, 0.0625, 0.125)
    head, _, line = table([dict(scene="s", seed=0, variant="v", status="ok", **row)]).splitlines()
    cells = [c.strip() for c in line.split("|")]
    names = [c.strip() for c in head.split("|")]
    assert len(cells) == len(names)
    assert cells[names.index("NVS seen px dB")] == "23.75"
    assert cells[names.index("static depth AbsRel DVS / NVS")] == "0.062 / 0.125"
