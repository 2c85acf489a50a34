"""A run's folder: the files it holds, and the checks before a run trains into it
(``check_run_folder``: nothing lost or mixed) or is resumed or evaluated on a scene
(``check_scene_of_run``: the scene it was trained on, by ``data.fingerprint``).

A run folder holds ``checkpoint.npz`` (the latest periodic checkpoint) and, once finished or
stopped by its time budget, ``final.npz``; ``config.json``, the run log (``log.csv``,
``log.json``), and after evaluation ``metrics.json``. The trainer writes into it only once its
set-up is done (``train/trainer.py``).
"""
from __future__ import annotations

from pathlib import Path

from d2gs_np.data import fingerprint
from d2gs_np.data.scene import Scene
from d2gs_np.train.checkpoint import load_checkpoint_meta

__all__ = ["CHECKPOINT_NAME", "FINAL_NAME", "CONFIG_NAME", "METRICS_NAME", "REPORT_NAME", "latest_checkpoint",
           "check_run_folder", "run_scene_record", "check_scene_of_run"]

CHECKPOINT_NAME = "checkpoint.npz"
FINAL_NAME = "final.npz"
CONFIG_NAME = "config.json"
METRICS_NAME = "metrics.json"  # written by evaluation.runs.evaluate_run
REPORT_NAME = "report.html"  # d2gs report's default output


def latest_checkpoint(run_dir):
    """The checkpoint of a run with the most steps (final.npz or checkpoint.npz), or None."""
    best, best_step = None, -1
    for name in (CHECKPOINT_NAME, FINAL_NAME):
        path = Path(run_dir) / name
        if path.exists():
            step = int(load_checkpoint_meta(path)["step"])
            if step > best_step:
                best, best_step = path, step
    return best


def check_run_folder(run_dir, resume: bool = False, overwrite: bool = False, flags=("resume=True", "overwrite=True")):
    """Refuse, before any work, to train into ``run_dir`` where that would lose or mix results:
    a folder that is not empty needs ``resume`` (go on from its latest checkpoint) or ``overwrite``
    (replace it); ``resume`` needs a checkpoint there. ``flags``: how the message names the two
    options (the CLI's ``--resume``, ``--overwrite``)."""
    run_dir = Path(run_dir)
    resume_flag, overwrite_flag = flags
    if resume and overwrite:
        raise ValueError(f"{resume_flag} continues the run in {run_dir} and {overwrite_flag} replaces it; give one "
                         "of them")
    if run_dir.exists() and not run_dir.is_dir():
        raise ValueError(f"run folder {run_dir} exists and is not a folder; choose another output folder")
    contents = sorted(p.name for p in run_dir.iterdir()) if run_dir.is_dir() else []
    if resume:
        if latest_checkpoint(run_dir) is None:
            raise FileNotFoundError(f"{resume_flag}: no checkpoint in {run_dir}; train without {resume_flag} first"
                                    + (f" ({overwrite_flag} to start over in it)" if contents else ""))
    elif contents and not overwrite:
        shown = ", ".join(contents[:6]) + (f" and {len(contents) - 6} more" if len(contents) > 6 else "")
        raise ValueError(f"run folder {run_dir} is not empty ({shown}); pass {resume_flag} to continue its training "
                         f"or {overwrite_flag} to replace it (kept until the new run's first checkpoint), or "
                         "choose a new folder")


def run_scene_record(meta: dict) -> dict:
    """The record (``data.fingerprint.scene_record``) of the scene a checkpoint was trained on;
    ``digest`` is None in checkpoints from before it was recorded."""
    return {"times": list(meta["times"]), "sizes": list(zip(meta["width"], meta["height"])),
            "digest": meta.get("scene_digest")}


def check_scene_of_run(meta: dict, scene: Scene, run_dir, action: str, fix: str, record=None) -> list:
    """Raise ValueError naming what differs when ``scene`` is not the scene of the run whose
    checkpoint ``meta`` is (``action``: what was asked, ``fix``: what to do instead); else return
    notes (another folder holding the same frames; a run without an image digest).
    ``record``: the scene's ``fingerprint.scene_record`` if already computed."""
    record = fingerprint.scene_record(scene) if record is None else record
    saved_root = meta.get("scene_root")
    diffs = fingerprint.differences(run_scene_record(meta), record)
    if diffs:
        where = f"scene {scene.root}" if scene.root is not None else "the scene"
        raise ValueError(f"{action}: {where} is not the scene run {run_dir} was trained on"
                         + (f" ({saved_root})" if saved_root else "") + f": {'; '.join(diffs)}; {fix}")
    notes = []
    if meta.get("scene_digest") is None:
        notes.append("the run's checkpoint records no image digest (an older run): the scene was checked on frame "
                     "count, times and image sizes only")
    elif scene.root is not None and saved_root and Path(scene.root).resolve() != Path(saved_root):
        notes.append(f"scene folder {Path(scene.root).resolve()} is not the run's ({saved_root}) but holds the same "
                     "frames (image digest)")
    return notes
