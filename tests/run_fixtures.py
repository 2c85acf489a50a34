"""Helpers for training-run tests (importable from tests/, see conftest.py)."""
import shutil

# What a run folder needs to resume: the latest checkpoint, the config and the log so far.
RESUME_FILES = ("checkpoint.npz", "config.json", "log.json", "log.csv")


def copy_run_for_resume(src, dst):
    """Copy the resume files of run folder ``src`` into a new folder ``dst`` (created here), so a
    test can resume the run from its checkpoint while ``src`` keeps the uninterrupted run."""
    dst.mkdir()
    for name in RESUME_FILES:
        shutil.copy(src / name, dst / name)
    return dst
