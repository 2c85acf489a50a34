"""A run's set-up (train/setup.py): it returns the documented record, writes nothing into the run
folder (fresh, over an earlier run, resumed), and builds the plugins passed as builders with the
run's context, through which they note into the run log."""
import dataclasses
import inspect
import json
from pathlib import Path

import pytest

from d2gs_np.data.synthetic import make_scene
from d2gs_np.optim.adam import AdamConfig
from d2gs_np.train.config import ExperimentConfig, LossConfig, PoseSolverConfig, TrainConfig
from d2gs_np.train.log import RunLog
from d2gs_np.train.plugins import Plugin, RunContext
from d2gs_np.train.schedule import TargetCache
from d2gs_np.train.setup import RunSetup, set_up_run
from d2gs_np.train.stages import Planner
from d2gs_np.train.state import StepRecord, TrainState
from d2gs_np.train.trainer import Trainer

TINY = dict(width=96, height=54, num_frames=6)  # SIFT finds matches at this size (L_reproj, the pose solver)
FIELDS = ["context", "log", "scene_record", "terms", "plugins", "state", "step", "seconds", "position_extent",
          "planner", "adam_config", "cache", "camera_row_scales", "resumed_from"]


def _config(iters=2, **train):
    base = dict(iters=iters, quiet=True, eval_every=1, log_every=1, checkpoint_every=0, prune_every=1)
    base.update(train)
    # every plugin a run can have: held-out PSNR, pruning, the pose solver, L_reproj's matches and depths
    return ExperimentConfig(train=TrainConfig(**base), loss=LossConfig(lambda_reproj=0.05),
                            pose_solver=PoseSolverConfig(mode="on", every=1, min_steps=1))


@pytest.fixture(scope="module")
def scene():
    return make_scene("static", 0, **TINY)


@pytest.fixture(scope="module")
def finished(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("setup") / "run"
    Trainer(scene, _config(), run).run()
    return run


def _snapshot(folder):
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def test_the_set_up_returns_its_documented_fields_and_writes_nothing(scene, tmp_path):
    run_dir = tmp_path / "new"
    setup = set_up_run(scene, _config(), run_dir)
    assert not run_dir.exists()
    assert [f.name for f in dataclasses.fields(RunSetup)] == FIELDS
    assert _commented_fields() == set(FIELDS)  # each field says what it holds
    assert isinstance(setup.context, RunContext) and isinstance(setup.log, RunLog)
    assert isinstance(setup.state, TrainState) and isinstance(setup.planner, Planner)
    assert isinstance(setup.adam_config, AdamConfig) and isinstance(setup.cache, TargetCache)
    assert setup.context.run_dir == run_dir and setup.context.scene is scene
    assert setup.context.note == setup.log.note  # what plugins note goes to the run log
    assert (setup.step, setup.seconds, setup.resumed_from) == (0, 0.0, None)
    assert [t.name for t in setup.terms] == ["photometric", "freq", "reproj"]
    assert [p.name for p in setup.plugins] == ["heldout_psnr", "gradient_statistics", "prune", "densify", "pose_solver",
                                              "reproj_depths"]
    assert setup.log.fields[-3:] == ("loss_photometric", "loss_freq", "loss_reproj")
    assert sorted(setup.adam_config.lrs) == sorted(setup.state.params)
    assert setup.scene_record["digest"] and setup.state.model.num_gaussians() > 0
    assert any(n.startswith("pose solver: on") for n in setup.log.notes)


def _commented_fields():
    """The names of RunSetup's fields declared with a comment beside them."""
    lines = inspect.getsource(RunSetup).splitlines()
    return {line.split(":")[0].strip() for line in lines if line.startswith("    ") and "  # " in line
            and not line.strip().startswith(('"', "#"))}


def test_the_set_up_over_an_earlier_run_or_to_resume_it_leaves_the_folder_as_it_was(scene, finished, tmp_path):
    before = _snapshot(finished)
    assert {"final.npz", "config.json", "log.json", "pose_solver.json"} <= set(before)
    assert any(name.startswith("correspond") for name in before)  # the matches' cache, written by the steps
    set_up_run(scene, _config(), finished, overwrite=True)
    assert _snapshot(finished) == before
    resumed = set_up_run(scene, _config(iters=3), finished, resume=True)
    assert _snapshot(finished) == before
    assert resumed.step == 2 and resumed.resumed_from == finished / "final.npz" and resumed.seconds > 0
    assert any(n.startswith(f"resumed from {finished / 'final.npz'}") for n in resumed.log.notes)
    with pytest.raises(ValueError, match="not empty"):
        set_up_run(scene, _config(), finished)
    assert _snapshot(finished) == before


class Noter(Plugin):
    """A plugin built from the run's context: notes each step's loss into the run log."""

    name = "noter"

    def __init__(self, context: RunContext):
        self.note, self.extent = context.note, context.extent

    def on_step(self, state):
        assert isinstance(state.record, StepRecord)
        self.note(f"noter: step {state.step}, loss {state.record.loss:.6g}")
        return state


def test_a_plugin_built_with_the_run_context_notes_into_the_run_log(tmp_path):
    scene = make_scene("sharp", 0, width=48, height=27, num_frames=6)
    cfg = ExperimentConfig(train=TrainConfig(iters=3, quiet=True, eval_every=0, log_every=1, checkpoint_every=0,
                                             prune_every=0))
    as_is = Plugin()  # a plugin is used as it is; a class or a function of the context is called with it
    built = []
    tr = Trainer(scene, cfg, tmp_path / "run", plugins=[Noter, as_is, lambda c: built.append(Noter(c)) or built[-1]])
    assert tr.plugins[-3:] == [tr.plugins[-3], as_is, built[0]] and isinstance(tr.plugins[-3], Noter)
    assert built[0].extent == tr.extent
    tr.run()
    losses = [r["loss"] for r in tr.log.rows]
    expect = [f"noter: step {s}, loss {loss:.6g}" for s, loss in enumerate(losses) for _ in range(2)]
    assert [n for n in tr.log.notes if n.startswith("noter:")] == expect
    notes = json.loads((tmp_path / "run" / "log.json").read_text())["notes"]
    assert [n for n in notes if n.startswith("noter:")] == expect
