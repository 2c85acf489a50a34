"""A run folder is never lost or mixed (issue #41, data loss 1-6): through the command line, a
command that fails leaves an existing run byte for byte as it was; one that succeeds leaves a
consistent run. The last test kills training (SIGKILL) ten times and resumes."""
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from d2gs_np.cli import main
from d2gs_np.train import run_folder
from d2gs_np.train import setup as train_setup
from d2gs_np.train import trainer as trainer_module
from d2gs_np.train.checkpoint import load_checkpoint, load_checkpoint_meta, save_checkpoint

REPO = Path(__file__).resolve().parents[2]
SCENE_ARGS = ["--preset", "dynamic", "--frames", "5", "--width", "40", "--height", "24"]
# Fast setup and one log row per step; every run of this file trains with it (a resume needs the
# same config).
FAST = {"init": {"dense_frames": 0, "random_fill_points": 300, "dynamic_points": 300}, "train": {"log_every": 1}}
TRAINED_STEPS = 4


def _make_scene(path, seed=3, *extra):
    assert main(["make-scene", str(path), "--seed", str(seed), *SCENE_ARGS, *extra]) == 0


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """(root, scene, run, config): a finished, evaluated run of TRAINED_STEPS steps. Tests that
    change a run work on a copy (``_copy``)."""
    root = tmp_path_factory.mktemp("kept")
    scene, run, cfg = root / "scene", root / "run", root / "fast.json"
    cfg.write_text(json.dumps(FAST))
    _make_scene(scene)
    assert main(["train", str(scene), "--out", str(run), "--iters", str(TRAINED_STEPS), "--config", str(cfg),
                 "--quiet"]) == 0
    assert main(["eval", str(run)]) == 0
    return root, scene, run, cfg


@pytest.fixture(scope="module")
def other_scenes(trained):
    """Scenes that are not the run's: same frames and size, other content; another image size;
    a byte-identical copy in another folder."""
    root, scene, _, _ = trained
    _make_scene(root / "other_content", 4)
    _make_scene(root / "other_size", 3, "--width", "48")
    shutil.copytree(scene, root / "copy")
    return root / "other_content", root / "other_size", root / "copy"


def _snapshot(folder):
    """Every file under ``folder``: its bytes and modification time."""
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _copy(run, dst):
    shutil.copytree(run, dst)
    return dst


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _step_of(path):
    return int(load_checkpoint_meta(path)["step"])


def _logged_steps(run):
    return [int(line.split(",")[0]) for line in (Path(run) / "log.csv").read_text().splitlines()[1:]]


# ------------------------------------------------------------------ 1. train into a finished run
def test_case1_train_into_a_finished_run_is_refused_before_the_scene_is_read(trained, tmp_path, capsys):
    root, scene, run, cfg = trained
    before = _snapshot(run)
    assert {"final.npz", "metrics.json", "config.json", "log.csv"} <= set(before)
    # a scene that does not exist: the run folder is refused first, before any scene is read
    assert main(["train", str(tmp_path / "no_scene"), "--out", str(run), "--iters", "3"]) == 2
    _one_line_error(capsys, "d2gs train: error:", str(run), "not empty", "--resume", "--overwrite")
    assert main(["train", str(scene), "--out", str(run), "--iters", "3", "--config", str(cfg)]) == 2
    _one_line_error(capsys, "final.npz", "--resume", "--overwrite")
    assert main(["train", str(scene), "--out", str(run), "--resume", "--overwrite"]) == 2
    _one_line_error(capsys, "--resume", "--overwrite", "one of them")
    assert _snapshot(run) == before


@pytest.mark.parametrize("bad, names", [(["--seed", "-1"], "--seed"), (["--time-budget", "nan"], "--time-budget"),
                                        (["--time-budget", "-5"], "--time-budget"), (["--iters", "0"], "--iters")])
def test_case1_a_typo_with_overwrite_leaves_the_run_as_it_was(trained, capsys, bad, names):
    root, scene, run, cfg = trained
    before = _snapshot(run)
    assert main(["train", str(scene), "--out", str(run), "--overwrite", "--config", str(cfg), *bad]) == 2
    _one_line_error(capsys, "d2gs train: error:", names)
    assert _snapshot(run) == before


def test_case1_a_setup_that_fails_with_overwrite_leaves_the_run_as_it_was(trained, tmp_path, capsys, monkeypatch):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    before = _snapshot(run)

    def fails(*args, **kwargs):
        raise ValueError("initialisation failed (test)")

    monkeypatch.setattr(train_setup.Model, "from_scene", fails)  # the long set-up, after every check
    assert main(["train", str(scene), "--out", str(run), "--overwrite", "--config", str(cfg), "--quiet"]) == 2
    _one_line_error(capsys, "initialisation failed")
    assert _snapshot(run) == before


def test_case1_overwrite_replaces_the_run_only_from_its_first_checkpoint(trained, tmp_path, monkeypatch):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    old_final = (run / "final.npz").read_bytes()
    seen = []
    real = trainer_module.save_checkpoint

    def spy(path, arrays, meta):
        # what the folder holds when each checkpoint is written: the old result until the first one
        final = run / "final.npz"
        seen.append((Path(path).name, int(meta["step"]), final.exists() and final.read_bytes() == old_final,
                     (run / "metrics.json").exists()))
        return real(path, arrays, meta)

    monkeypatch.setattr(trainer_module, "save_checkpoint", spy)
    assert main(["train", str(scene), "--out", str(run), "--overwrite", "--iters", "2", "--config", str(cfg),
                 "--quiet"]) == 0
    assert seen[0] == ("checkpoint.npz", 0, True, True), seen
    assert seen[-1][:2] == ("final.npz", 2) and not any(s[2] or s[3] for s in seen[1:]), seen
    assert _step_of(run / "final.npz") == 2 and not (run / "metrics.json").exists()
    assert _logged_steps(run) == [0, 1]
    assert json.loads((run / "config.json").read_text())["train"]["iters"] == 2
    assert json.loads((run / "log.json").read_text())["rows"][-1]["step"] == 1


# ------------------------------------------------------------------ 2. resume on another scene
def test_case2_resume_on_another_scene_is_refused_before_training(trained, other_scenes, tmp_path, capsys):
    root, scene, run, cfg = trained
    other_content, other_size, _ = other_scenes
    before = _snapshot(run)
    args = ["--out", str(run), "--resume", "--iters", "8", "--config", str(cfg), "--quiet"]
    assert main(["train", str(other_content), *args]) == 2
    _one_line_error(capsys, "--resume", str(other_content), "is not the scene run", "its images differ",
                    "resume with the run's scene")
    assert main(["train", str(other_size), *args]) == 2
    _one_line_error(capsys, "frame 0 is 48x24 pixels, the run's 40x24")
    assert _snapshot(run) == before


def test_case2_resume_from_a_copy_of_the_scene_goes_on(trained, other_scenes, tmp_path, capsys):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    copy = other_scenes[2]
    assert main(["train", str(copy), "--out", str(run), "--resume", "--iters", str(TRAINED_STEPS + 2),
                 "--config", str(cfg)]) == 0
    assert "holds the same frames" in capsys.readouterr().out
    assert _step_of(run / "final.npz") == TRAINED_STEPS + 2


def test_case2_a_checkpoint_without_a_digest_is_checked_on_what_it_records(trained, other_scenes, tmp_path,
                                                                           capsys):
    # a run from before image digests: frame count, times and sizes are still checked
    root, scene, run, cfg = trained
    other_content, other_size, _ = other_scenes
    run = _copy(run, tmp_path / "run")
    arrays, meta = load_checkpoint(run / "final.npz")
    del meta["scene_digest"]
    save_checkpoint(run / "final.npz", arrays, meta)
    before = _snapshot(run)
    args = ["--out", str(run), "--resume", "--iters", str(TRAINED_STEPS + 1), "--config", str(cfg)]
    assert main(["train", str(other_size), *args]) == 2
    _one_line_error(capsys, "48x24")
    assert _snapshot(run) == before
    assert main(["train", str(scene), *args]) == 0
    assert "records no image digest" in capsys.readouterr().out


# ------------------------------------------------------------------ 3. checkpoints on the wall clock
def _checkpoint_steps(monkeypatch):
    steps = []
    real = trainer_module.save_checkpoint

    def spy(path, arrays, meta):
        steps.append((Path(path).name, int(meta["step"])))
        return real(path, arrays, meta)

    monkeypatch.setattr(trainer_module, "save_checkpoint", spy)
    return steps


@pytest.mark.parametrize("seconds, expected", [
    (1e-6, [("checkpoint.npz", s) for s in range(4)] + [("final.npz", 4)]),  # every step takes longer
    (0, [("checkpoint.npz", 0), ("final.npz", 4)]),  # off: the first checkpoint and the final one
])
def test_case3_checkpoints_on_a_wall_clock_period(trained, tmp_path, monkeypatch, seconds, expected):
    root, scene, run, _ = trained
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({**FAST, "train": {**FAST["train"], "checkpoint_every": 0,
                                                  "checkpoint_seconds": seconds}}))
    steps = _checkpoint_steps(monkeypatch)
    assert main(["train", str(scene), "--out", str(tmp_path / "run"), "--iters", "4", "--config", str(cfg),
                 "--quiet"]) == 0
    assert steps == expected
    assert not list((tmp_path / "run").glob(".*.tmp"))


def test_case3_the_wall_clock_period_is_validated(trained, tmp_path, capsys):
    root, scene, run, _ = trained
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"train": {"checkpoint_seconds": -1}}))
    assert main(["train", str(scene), "--out", str(tmp_path / "run"), "--config", str(cfg)]) == 2
    _one_line_error(capsys, "checkpoint_seconds", "-1")
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ 4. Ctrl-C
def test_case4_ctrl_c_during_setup_exits_130_and_changes_nothing(trained, tmp_path, capsys, monkeypatch):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    before = _snapshot(run)

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer_module, "warm_up", ctrl_c)  # the JIT warm-up: the last part of the setup
    assert main(["train", str(scene), "--out", str(run), "--overwrite", "--config", str(cfg), "--quiet"]) == 130
    _one_line_error(capsys, "d2gs train: interrupted: before training started", f"nothing in {run} was changed")
    assert _snapshot(run) == before


def _env():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))


def _d2gs(*args):
    return [sys.executable, "-m", "d2gs_np", *map(str, args)]


def _wait_for_step(proc, run, step, started, timeout=120.0):
    """Wait until ``proc`` (started at ``started``, ``time.time()``) has logged a row of ``step`` or
    later in ``run``; ``step`` -1: until it has written the log's header (its first write into the
    run folder follows its first checkpoint). An earlier process's rows do not count."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and proc.poll() is None:
        try:
            if (run / "log.csv").stat().st_mtime >= started and max(_logged_steps(run), default=-1) >= step:
                return
        except (FileNotFoundError, ValueError):  # not there yet, or a row being written
            pass
        time.sleep(0.01)
    raise AssertionError(f"no log row of step {step} in {run} after {timeout:.0f}s (exit {proc.poll()})")


def test_case4_ctrl_c_while_training_writes_a_checkpoint_and_says_how_to_resume(trained, tmp_path):
    root, scene, run, cfg = trained
    run = tmp_path / "run"
    started = time.time()
    iters = 500
    # SIGINT at its default in the run, as in a terminal's foreground job: under a test suite started
    # as a background job SIGINT is ignored, and the trainer then leaves it so (no handler to test)
    proc = subprocess.Popen(_d2gs("train", scene, "--out", run, "--iters", iters, "--config", cfg, "--quiet"),
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_step(proc, run, 2, started)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    step = _step_of(run / "checkpoint.npz")
    assert 2 < step < iters and not (run / "final.npz").exists()
    prefix = f"d2gs train: interrupted: checkpoint of step {step} written to {run / 'checkpoint.npz'}; continue with: "
    assert lines[0].startswith(prefix), lines[0]
    command = shlex.split(lines[0][len(prefix):])
    assert command[:2] == ["d2gs", "train"] and "--resume" in command and str(run) in command
    assert max(_logged_steps(run)) == step - 1  # the log holds the steps the checkpoint holds
    # the printed command resumes (with a shorter schedule, so that the test ends soon)
    command[command.index("--iters") + 1] = str(step + 2)
    done = subprocess.run([sys.executable, "-m", "d2gs_np", *command[1:]], env=_env(), capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert _step_of(run / "final.npz") == step + 2
    assert _logged_steps(run) == list(range(step + 2))


# ------------------------------------------------------------------ 5. metrics of a resumed run
def test_case5_a_resumed_run_drops_its_old_metrics_and_report_evaluates_it(trained, tmp_path):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    assert json.loads((run / "metrics.json").read_text())["steps"] == TRAINED_STEPS
    assert main(["train", str(scene), "--out", str(run), "--resume", "--iters", str(TRAINED_STEPS + 2),
                 "--config", str(cfg), "--quiet"]) == 0
    assert not (run / "metrics.json").exists()
    assert main(["report", str(run)]) == 0  # no metrics: the report evaluates the run as it is now
    assert json.loads((run / "metrics.json").read_text())["steps"] == TRAINED_STEPS + 2
    assert (run / "report.html").stat().st_size > 0


def test_case5_resuming_a_finished_run_with_nothing_to_do_changes_nothing(trained, tmp_path):
    root, scene, run, cfg = trained
    run = _copy(run, tmp_path / "run")
    before = _snapshot(run)
    assert main(["train", str(scene), "--out", str(run), "--resume", "--iters", str(TRAINED_STEPS),
                 "--config", str(cfg), "--quiet"]) == 0
    assert _snapshot(run) == before


# ------------------------------------------------------------------ 6. eval on another scene
def test_case6_eval_on_another_scene_is_refused_and_keeps_the_metrics(trained, other_scenes, tmp_path, capsys):
    root, scene, run, cfg = trained
    other_content, other_size, copy = other_scenes
    before = _snapshot(run)
    assert main(["eval", str(run), "--scene", str(other_content)]) == 2
    _one_line_error(capsys, "d2gs eval: error: --scene", "its images differ", "run's own scene")
    assert main(["eval", str(run), "--scene", str(other_size)]) == 2
    _one_line_error(capsys, "48x24 pixels")
    assert _snapshot(run) == before
    # a copy of the run's scene in another folder is the same scene
    run = _copy(run, tmp_path / "run")
    metrics = (run / "metrics.json").read_text()
    assert main(["eval", str(run), "--scene", str(copy)]) == 0
    assert "holds the same frames" in capsys.readouterr().err
    assert json.loads((run / "metrics.json").read_text()) == json.loads(metrics)


def test_case6_eval_refuses_the_runs_scene_folder_rewritten_since_training(trained, tmp_path, capsys):
    root, scene, run, cfg = trained
    moved = tmp_path / "scene"
    shutil.copytree(scene, moved)
    run = _copy(run, tmp_path / "run")
    arrays, meta = load_checkpoint(run / "final.npz")
    save_checkpoint(run / "final.npz", arrays, {**meta, "scene_root": str(moved.resolve())})
    _make_scene(moved, 5, "--overwrite")  # the folder the run was trained on now holds other frames
    before = _snapshot(run)
    assert main(["eval", str(run)]) == 2
    _one_line_error(capsys, "d2gs eval: error: the run's own scene", "its images differ", "changed since training")
    assert _snapshot(run) == before


# ------------------------------------------------------------------ kill and resume
@pytest.mark.slow
def test_sigkill_at_random_moments_then_resume_loses_at_most_one_checkpoint_period(trained, tmp_path):
    root, scene, _, _ = trained
    iters, every = 60, 4
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({**FAST, "train": {**FAST["train"], "checkpoint_every": every,
                                                  "checkpoint_seconds": 0}}))
    run = tmp_path / "run"
    # The ten moments, drawn up front, in a random order: one in the start-up (imports, setup),
    # two just after the run's first write into its folder (its first checkpoint, config and log),
    # seven within the step k steps after the resumed one. A kill lets a process get a few steps
    # further at most, so ten fit in the schedule.
    rng = np.random.default_rng(41)
    plan = ([("start-up", rng.uniform(0.0, 1.0))] + [("opened", rng.uniform(0.0, 0.05)) for _ in range(2)]
            + [("step", int(rng.integers(0, 4)), rng.uniform(0.0, 0.05)) for _ in range(7)])
    plan = [plan[i] for i in rng.permutation(len(plan))]
    kills = []
    for moment in plan:
        latest = run_folder.latest_checkpoint(run) if run.exists() else None
        start = _step_of(latest) if latest is not None else 0
        how = ["--resume"] if latest is not None else (["--overwrite"] if run.exists() else [])
        started = time.time()
        proc = subprocess.Popen(_d2gs("train", scene, "--out", run, "--iters", iters, "--config", cfg, "--quiet",
                                      *how), env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        if moment[0] == "start-up":
            time.sleep(moment[1])
        else:
            _wait_for_step(proc, run, -1 if moment[0] == "opened" else start + moment[1], started)
            time.sleep(moment[-1])
        assert proc.poll() is None, f"the run ended (exit {proc.returncode}) before its kill: {proc.stderr.read()}"
        proc.kill()
        proc.wait()
        proc.stderr.close()
        done = max(_logged_steps(run), default=-1) + 1 if (run / "log.csv").exists() else 0
        latest = run_folder.latest_checkpoint(run) if run.exists() else None
        kept = _step_of(latest) if latest is not None else 0
        kills.append((moment[0], start, done, kept))
        # never behind the state it resumed from; nothing lost beyond the last checkpoint period
        assert start <= kept and done - kept <= every, kills
    assert sum(done > start for _, start, done, _ in kills) >= 5, f"too few kills came after a step: {kills}"
    print("kills (moment, resumed from, steps done, checkpoint kept):", kills)
    finish = subprocess.run(_d2gs("train", scene, "--out", run, "--iters", iters, "--config", cfg, "--quiet",
                                  "--resume"), env=_env(), capture_output=True, text=True, timeout=600)
    assert finish.returncode == 0, finish.stderr
    assert _logged_steps(run) == list(range(iters))  # each step once, in order
    assert [r["step"] for r in json.loads((run / "log.json").read_text())["rows"]] == list(range(iters))
    assert _step_of(run / "final.npz") == iters
    assert not list(run.glob(".*.tmp"))
    # and the model is the uninterrupted run's, bit for bit
    assert main(["train", str(scene), "--out", str(tmp_path / "once"), "--iters", str(iters), "--config", str(cfg),
                 "--quiet"]) == 0
    a, _ = load_checkpoint(run / "final.npz")
    b, _ = load_checkpoint(tmp_path / "once" / "final.npz")
    assert sorted(a) == sorted(b)
    for name in b:
        if name.startswith("params/"):
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)
