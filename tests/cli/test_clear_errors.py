"""Issue #41, cases 10 and 12: every refusal of the CLI is one line on stderr,
``d2gs CMD: error: ...``, naming the problem and the fix, with status 2 (1 stays reserved for a
reference check that ran and failed), raised before any work, with no traceback, and a failing
command leaves an existing run exactly as it was.

Read-only folders: these tests run as root, for whom a chmod'ed folder is still writable, so
a real permission error cannot be provoked. The commands decide writability with ``os.access``
(what the kernel answers for a non-root user); the tests monkeypatch ``os.access`` to deny write
access to one folder, and check that the command refuses before writing anything.
"""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from d2gs_np.cli import main

REPO = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------------------- helpers
def run_cli(argv, capsys):
    """(status, stdout, stderr) of ``main(argv)``; argparse's refusals exit through SystemExit."""
    try:
        status = main([str(a) for a in argv])
    except SystemExit as e:
        status = e.code
    out, err = capsys.readouterr()
    return status, out, err


def assert_one_line_error(status, err, command, *needles):
    """Status 2, exactly one stderr line ``d2gs COMMAND: error: ...`` holding every needle."""
    lines = err.strip().splitlines()
    assert status == 2, (status, err)
    assert len(lines) == 1, err
    assert lines[0].startswith(f"d2gs {command}: error: "), lines[0]
    assert "Traceback" not in err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def snapshot(folder):
    """{relative path: (bytes, mtime_ns)} of every file under ``folder``."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def deny_writes(monkeypatch, folder):
    """Make ``os.access`` report ``folder`` as not writable (root ignores the mode bits; see the
    module docstring)."""
    real = os.access
    target = Path(folder).resolve()

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and Path(path).resolve() == target:
            return False
        return real(path, mode, *args, **kwargs)
    monkeypatch.setattr(os, "access", access)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny scene, a run trained on it for a few steps and evaluated once (so metrics.json exists)."""
    root = tmp_path_factory.mktemp("clear_errors")
    scene, run = root / "scene", root / "run"
    assert main(["make-scene", str(scene), "--preset", "dynamic", "--seed", "3",
                 "--frames", "5", "--width", "40", "--height", "24"]) == 0
    assert main(["train", str(scene), "--out", str(run), "--iters", "4", "--quiet"]) == 0
    assert main(["eval", str(run)]) == 0
    return scene, run


@pytest.fixture(scope="module")
def golden(tmp_path_factory):
    """A one-case refcheck export."""
    gold = tmp_path_factory.mktemp("refcheck") / "gold"
    assert main(["refcheck", "export", str(gold), "--cases", "random_small"]) == 0
    return gold


def _commands(run, scene, out):
    """Each writing command with its output at ``out`` (a folder, or a file for render,
    export-ply and report): (name, argv, output is a file)."""
    return [
        ("train", ["train", scene, "--out", out, "--iters", "2", "--quiet"], False),
        ("render", ["render", run, "--time", "0.5", "--out", Path(out).with_suffix(".png")], True),
        ("export-ply", ["export-ply", run, "--time", "0.5", out], True),
        ("make-scene", ["make-scene", out, "--frames", "5", "--width", "40", "--height", "24"], False),
        ("import-video", ["import-video", scene / "images", out], False),
        ("demo", ["demo", "--quick", "--out", out], False),
        ("experiment", ["experiment", "baselines", "--out", out, "--scenes", "dynamic", "--iters", "2"], False),
        ("report", ["report", run, "--out", Path(out).with_suffix(".html")], True),
        ("refcheck export", ["refcheck", "export", out, "--cases", "random_small"], False),
    ]


COMMAND_NAMES = [c[0] for c in _commands(Path("r"), Path("s"), Path("o"))]


# ------------------------------------------------------------------------------ case 10
@pytest.mark.parametrize("command", COMMAND_NAMES)
@pytest.mark.parametrize("where", ["wrong_kind", "under_a_file"])
def test_case10_out_is_a_file_or_sits_under_a_file(trained, tmp_path, capsys, command, where):
    """--out that exists as a file (a folder for file outputs), or a path under a regular file:
    one line naming the path and the fix, before any work; the run and the file untouched."""
    scene, run = trained
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")

    def command_with_output(out):
        return {c[0]: c for c in _commands(run, scene, out)}[command][1:]
    argv, is_file = command_with_output(blocker / "out")
    entries = {blocker}
    if where == "wrong_kind" and is_file:  # a folder where the file should go
        argv, _ = command_with_output(tmp_path / "taken")
        target = next(Path(a) for a in argv if str(a).startswith(str(tmp_path / "taken")))
        target.mkdir()
        entries.add(target)
        expect = f"{target} is a folder; give the path of a file"
    elif where == "wrong_kind":
        argv, _ = command_with_output(blocker)
        expect = f"{blocker} is a file, not a folder; choose a folder path (or remove the file)"
    else:
        expect = f"sits under {blocker}, which is a file, not a folder; choose a path outside it"
    before = snapshot(run)
    status, out, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, command, expect)
    assert blocker.read_text() == "not a folder"
    assert snapshot(run) == before
    assert set(tmp_path.iterdir()) == entries and all(not any(e.iterdir()) for e in entries if e.is_dir())


@pytest.mark.parametrize("command", COMMAND_NAMES)
def test_case10_read_only_output_folder(trained, tmp_path, capsys, monkeypatch, command):
    """An output under a folder the user cannot write (os.access mocked: we run as root, see the
    module docstring): refused up front, nothing written into the folder."""
    scene, run = trained
    ro = tmp_path / "readonly"
    ro.mkdir()
    _, argv, _ = {c[0]: c for c in _commands(run, scene, ro / "out")}[command]
    deny_writes(monkeypatch, ro)
    before = snapshot(run)
    status, out, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, command, f"the folder {ro} is not writable", "fix its permissions")
    assert list(ro.iterdir()) == []
    assert snapshot(run) == before


@pytest.mark.parametrize("command", ["train", "demo", "experiment"])
def test_case10_config_is_a_directory(trained, tmp_path, capsys, command):
    """--config naming a folder (here a run folder, whose config.json is suggested): one line,
    before the scene is read or made."""
    scene, run = trained
    out = tmp_path / "out"
    argv = {"train": ["train", scene, "--out", out, "--config", run],
            "demo": ["demo", "--quick", "--out", out, "--config", run],
            "experiment": ["experiment", "baselines", "--out", out, "--scenes", "dynamic", "--iters", "2",
                           "--config", run]}[command]
    before = snapshot(run)
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, command, f"config file {run} is a folder",
                          f"pass the config JSON file (e.g. {run / 'config.json'})")
    assert not (out / "scene").exists() and not (out / "run").exists() and not (out / "runs").exists()
    assert snapshot(run) == before


def test_case10_eval_on_a_read_only_run(trained, capsys, monkeypatch):
    """d2gs eval on a run folder it cannot write refuses before the evaluation (it used to fail
    after it, writing metrics.json): the scene is never read, metrics.json keeps its bytes."""
    import d2gs_np.evaluation.runs as evaluate_module

    _, run = trained
    calls = []
    monkeypatch.setattr(evaluate_module, "load_scene", lambda *a, **k: calls.append("load_scene"))
    monkeypatch.setattr(evaluate_module, "evaluate", lambda *a, **k: calls.append("evaluate"))
    deny_writes(monkeypatch, run)
    before = snapshot(run)
    status, out, err = run_cli(["eval", run], capsys)
    assert_one_line_error(status, err, "eval", f"metrics file {run / 'metrics.json'}",
                          f"the folder {run} is not writable")
    assert calls == [] and out == ""
    assert snapshot(run) == before


@pytest.mark.parametrize("name", ["noext", "frame.", "frame.gif"])
def test_case10_render_out_without_an_image_extension(trained, tmp_path, capsys, name):
    """render --out without an image extension: one line suggesting NAME.png (OpenCV used to fail
    with a traceback after the render)."""
    _, run = trained
    out = tmp_path / name
    status, _, err = run_cli(["render", run, "--time", "0.5", "--out", out], capsys)
    assert_one_line_error(status, err, "render", f"--out {out} needs an image extension (.png",
                          f"e.g. --out {out.with_suffix('.png')}")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("damage", ["truncated", "garbage"])
def test_case10_refcheck_compare_on_a_truncated_npz_exits_2_not_1(golden, tmp_path, capsys, damage):
    """A damaged results file is a usage error (2, one line naming the file), not a failed check
    (1): the check never ran. A result that differs still exits 1."""
    theirs = tmp_path / "theirs"
    shutil.copytree(golden, theirs)
    npz = theirs / "random_small.npz"
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2] if damage == "truncated" else b"\x00" * 256)
    status, _, err = run_cli(["refcheck", "compare", golden, theirs], capsys)
    assert_one_line_error(status, err, "refcheck compare", f"refcheck case file {npz} is not a readable .npz",
                          "write it again")
    # the contrast: a readable file with a wrong value is a failed check, status 1
    z = dict(np.load(golden / "random_small.npz"))
    z["out.image"] = z["out.image"] + 1.0
    np.savez(npz, **z)
    status, out, err = run_cli(["refcheck", "compare", golden, theirs], capsys)
    assert status == 1 and "FAILED random_small out.image" in out and "error:" not in err


def test_case10_real_process_prints_one_line_and_exits_2(golden, tmp_path):
    """The same in a real process (python -m d2gs_np): a truncated npz used to print a BadZipFile
    traceback and exit 1."""
    theirs = tmp_path / "theirs"
    shutil.copytree(golden, theirs)
    npz = theirs / "random_small.npz"
    npz.write_bytes(npz.read_bytes()[:100])
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "d2gs_np", "refcheck", "compare", str(golden), str(theirs)],
                          capture_output=True, text=True, env=env, cwd=tmp_path)
    assert_one_line_error(proc.returncode, proc.stderr, "refcheck compare", str(npz))


# ------------------------------------------------------------------------------ case 12
@pytest.mark.parametrize("argv, flag, expect", [
    (["train", "{scene}", "--out", "{out}", "--seed", "-1"], "--seed", "must be an integer >= 0; got '-1'"),
    (["make-scene", "{out}", "--seed", "-1"], "--seed", "must be an integer >= 0"),
    (["demo", "--quick", "--out", "{out}", "--seed", "-1"], "--seed", "must be an integer >= 0"),
    (["experiment", "baselines", "--out", "{out}", "--scenes", "dynamic", "--iters", "2", "--seeds", "0", "-1"],
     "--seeds", "must be an integer >= 0"),
    (["train", "{scene}", "--out", "{out}", "--iters", "0"], "--iters", "must be an integer >= 1; got '0'"),
    (["train", "{scene}", "--out", "{out}", "--n", "x"], "--n", "must be an integer >= 1; got 'x'"),
    (["make-scene", "{out}", "--frames", "0"], "--frames", "must be an integer >= 1"),
    (["report", "{run}", "--frames", "0"], "--frames", "must be an integer >= 1"),
    (["import-video", "{scene}/images", "{out}", "--stride", "0"], "--stride", "must be an integer >= 1"),
])
def test_case12_negative_seed_and_counts_name_their_flag(trained, tmp_path, capsys, argv, flag, expect):
    """--seed -1 used to fail after the scene was read with NumPy's 'expected non-negative
    integer', naming no flag; now argparse refuses it, naming the flag, in one line, status 2."""
    scene, run = trained
    out = tmp_path / "out"
    argv = [a.format(scene=scene, run=run, out=out) for a in argv]
    before = snapshot(run)
    status, _, err = run_cli(argv, capsys)
    command = argv[0]
    assert_one_line_error(status, err, command, f"argument {flag}: {expect}", f"(see 'd2gs {command} --help')")
    assert not out.exists() and snapshot(run) == before


def test_case12_seed_into_an_existing_run_leaves_it_alone(trained, capsys):
    """d2gs train SCENE --out EXISTING_RUN --seed -1 refuses without touching the run."""
    scene, run = trained
    before = snapshot(run)
    status, _, err = run_cli(["train", scene, "--out", run, "--seed", "-1"], capsys)
    assert_one_line_error(status, err, "train", "argument --seed")
    assert snapshot(run) == before


@pytest.mark.parametrize("argv, flag", [
    (["train", "{missing}", "--out", "{out}", "--time-budget", "nan"], "--time-budget"),
    (["train", "{missing}", "--out", "{out}", "--time-budget", "inf"], "--time-budget"),
    (["train", "{missing}", "--out", "{out}", "--time-budget", "-5"], "--time-budget"),
    (["demo", "--quick", "--out", "{out}", "--time-budget", "nan"], "--time-budget"),
    (["experiment", "baselines", "--out", "{out}", "--scenes", "dynamic", "--budget", "nan"], "--budget"),
])
def test_case12_time_budget_nan_is_refused_up_front(tmp_path, capsys, argv, flag):
    """--time-budget nan passed the up-front check and failed 20-30 s later, after the scene
    was read and the bundle adjustment ran. Refused now before anything (the scene folder does
    not even exist: the budget is what is reported)."""
    out = tmp_path / "out"
    argv = [a.format(missing=tmp_path / "no_scene", out=out) for a in argv]
    status, _, err = run_cli(argv, capsys)
    assert_one_line_error(status, err, argv[0], f"argument {flag}: must be a finite number > 0; got")
    assert not out.exists()


def test_case12_time_budget_nan_in_a_config_file_is_refused_up_front(tmp_path, capsys):
    """The same budget from a config file (JSON allows NaN): a config error, before the scene."""
    cfg = tmp_path / "c.json"
    cfg.write_text('{"train": {"time_budget": NaN}}')
    out = tmp_path / "out"
    status, _, err = run_cli(["train", tmp_path / "no_scene", "--out", out, "--config", cfg], capsys)
    assert_one_line_error(status, err, "train", "TrainConfig.time_budget must be a finite number > 0 (seconds); got nan")
    assert not out.exists()


@pytest.mark.parametrize("what", ["pose_json", "cases_json", "object_array", "pose_not_object"])
def test_case12_bad_json_or_npz_names_the_file(trained, golden, tmp_path, capsys, what):
    """An invalid --pose JSON, a corrupt cases.json or an object array: the message names the
    file (it used to be json's or NumPy's bare text)."""
    _, run = trained
    if what in ("pose_json", "pose_not_object"):
        bad = tmp_path / "pose.json"
        bad.write_text('{"cam_T_world": [[1, 0' if what == "pose_json" else "[1, 2, 3]")
        argv, command = ["render", run, "--time", "0.5", "--pose", bad, "--out", tmp_path / "r.png"], "render"
        expect = [f"pose file {bad}", "fix the syntax" if what == "pose_json" else "must hold a JSON object"]
    elif what == "cases_json":
        gold = tmp_path / "gold"
        shutil.copytree(golden, gold)
        bad = gold / "cases.json"
        bad.write_text(bad.read_text()[:50])
        argv, command = ["refcheck", "compare", gold, golden], "refcheck compare"
        expect = [f"{bad} is not valid JSON", f"export the folder again ('d2gs refcheck export {gold}')"]
    else:
        theirs = tmp_path / "theirs"
        shutil.copytree(golden, theirs)
        bad = theirs / "random_small.npz"
        z = dict(np.load(bad))
        z["grad.means"] = np.array([object(), 1.0], dtype=object)
        np.savez(bad, **z)
        argv, command = ["refcheck", "compare", golden, theirs], "refcheck compare"
        expect = [f"{bad}: array 'grad.means' holds Python objects", "write plain numeric arrays"]
    status, _, err = run_cli(argv, capsys)
    line = assert_one_line_error(status, err, command, *expect)
    assert "allow_pickle" not in line
    assert not (tmp_path / "r.png").exists()


def test_case12_ascii_ply_message_is_a_whole_sentence_with_the_fix(trained, tmp_path, capsys):
    """A scene whose sparse points are an ASCII PLY: the message ended in 're-save it so'; now it
    names the format and how to re-save, before training starts."""
    scene, _ = trained
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    doc = json.loads((sc / "transforms.json").read_text())
    doc["ply_file_path"] = "points.ply"
    (sc / "transforms.json").write_text(json.dumps(doc))
    (sc / "points.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                                   "property float z\nend_header\n0 0 0\n")
    out = tmp_path / "run"
    status, _, err = run_cli(["train", sc, "--out", out, "--iters", "2"], capsys)
    line = assert_one_line_error(status, err, "train", f"{sc / 'points.ply'}: ASCII PLY point clouds are not "
                                 "supported; re-save it as binary little-endian PLY")
    assert line.rstrip().endswith(")") and not line.rstrip().endswith("so")
    assert not out.exists()


@pytest.mark.parametrize("garbage", ["random_bytes", "object_array", "no_meta"])
def test_case12_garbage_checkpoint_gives_our_advice_not_numpys(trained, tmp_path, capsys, garbage):
    """A garbage final.npz: the message named NumPy's 'allow_pickle' (unsafe, and never what our
    checkpoints need); now it says what is wrong and to retrain. The run is left alone."""
    _, run = trained
    bad_run = tmp_path / "run"
    shutil.copytree(run, bad_run)
    final = bad_run / "final.npz"
    if garbage == "random_bytes":
        final.write_bytes(np.random.default_rng(0).bytes(1000))
    elif garbage == "object_array":
        np.savez(final, a=np.array([object()], dtype=object))
    else:
        np.savez(final, a=np.zeros(3))
    before = snapshot(bad_run)
    for argv, command in ((["eval", bad_run], "eval"),
                          (["render", bad_run, "--time", "0.5", "--out", tmp_path / "r.png"], "render")):
        status, _, err = run_cli(argv, capsys)
        line = assert_one_line_error(status, err, command, f"checkpoint {final} is unreadable",
                                     "delete it and retrain")
        assert "allow_pickle" not in line and "pickle" not in line
    assert snapshot(bad_run) == before and not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("what", ["run_is_a_file", "pose_is_a_folder", "export_is_a_file", "results_is_a_file",
                                  "image_is_a_folder"])
def test_case12_a_file_or_folder_is_not_said_not_to_exist(trained, golden, tmp_path, capsys, what):
    """A path that exists but is the wrong kind used to be reported as 'does not exist' (or a
    traceback); the message now says what it is."""
    scene, run = trained
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    a_folder = tmp_path / "a_folder"
    a_folder.mkdir()
    if what == "run_is_a_file":
        argv, command, expect = ["eval", a_file], "eval", f"run folder {a_file} is a file"
    elif what == "pose_is_a_folder":
        argv, command, expect = (["render", run, "--time", "0.5", "--pose", a_folder, "--out", tmp_path / "r.png"],
                                 "render", f"--pose {a_folder} is a folder; pass a pose JSON file")
    elif what == "export_is_a_file":
        argv, command, expect = (["refcheck", "compare", a_file, golden], "refcheck compare",
                                 f"refcheck folder {a_file} is a file, not a folder")
    elif what == "results_is_a_file":
        argv, command, expect = (["refcheck", "compare", golden, a_file], "refcheck compare",
                                 f"results folder {a_file} is a file")
    else:
        sc = tmp_path / "scene"
        shutil.copytree(scene, sc)
        doc = json.loads((sc / "transforms.json").read_text())
        rel = doc["frames"][0]["file_path"]
        (sc / rel).unlink()
        (sc / rel).mkdir()
        argv, command, expect = (["train", sc, "--out", tmp_path / "run"], "train",
                                 f"image path {sc / rel} is a folder, not a PNG file")
    status, _, err = run_cli(argv, capsys)
    line = assert_one_line_error(status, err, command, expect)
    assert "does not exist" not in line


def test_case12_make_scene_names_the_overwrite_flag(trained, tmp_path, capsys):
    """make-scene into a non-empty folder said 'pass overwrite=True' (a Python keyword); it names
    --overwrite now, and leaves the folder alone. With --overwrite it writes."""
    scene, _ = trained
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    before = snapshot(sc)
    argv = ["make-scene", sc, "--frames", "5", "--width", "40", "--height", "24"]
    status, _, err = run_cli(argv, capsys)
    line = assert_one_line_error(status, err, "make-scene", f"scene folder {sc} is not empty; pass --overwrite")
    assert "overwrite=True" not in line
    assert snapshot(sc) == before
    assert run_cli(argv + ["--overwrite"], capsys)[0] == 0


@pytest.mark.parametrize("frames, expect", [({"0": {}}, "its 'frames' is a JSON object"),
                                            ("images/", "its 'frames' is a JSON string"),
                                            (None, "it has none")])
def test_case12_frames_of_the_wrong_type_are_named(trained, tmp_path, capsys, frames, expect):
    """A 'frames' dict was reported as 'it has none'; the message now says what it is (and 'it has
    none' only when the key is missing)."""
    scene, _ = trained
    sc = tmp_path / "scene"
    shutil.copytree(scene, sc)
    doc = json.loads((sc / "transforms.json").read_text())
    if frames is None:
        del doc["frames"]
    else:
        doc["frames"] = frames
    (sc / "transforms.json").write_text(json.dumps(doc))
    status, _, err = run_cli(["train", sc, "--out", tmp_path / "run"], capsys)
    assert_one_line_error(status, err, "train", "must have a 'frames' list (one entry per image)", expect)
    assert not (tmp_path / "run").exists()


def test_case12_negative_test_pose_opt_is_an_error_with_status_2(trained, capsys):
    """eval --test-pose-opt -1 exited 1 with a bare message (SystemExit(str)); now argparse's
    one-line error naming the flag, status 2, and metrics.json untouched."""
    _, run = trained
    before = snapshot(run)
    status, out, err = run_cli(["eval", run, "--test-pose-opt", "-1"], capsys)
    assert_one_line_error(status, err, "eval", "argument --test-pose-opt: must be an integer >= 0; got '-1'")
    assert out == "" and snapshot(run) == before
