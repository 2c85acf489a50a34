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


TINY = dict(width=48, height=27, num_frames=6)  # a tiny clip of the "dynamic" preset: seconds to train


def tiny_dynamic_scene(trusted: bool, seed=0):
    """The "dynamic" preset at ``TINY`` size: true poses flagged as exact (``trusted``), or the
    preset's noisy ones."""
    from d2gs_np.data.synthetic import make_scene

    exact = dict(rot_noise_deg=0.0, trans_noise_fraction=0.0) if trusted else {}
    scene = make_scene("dynamic", seed, **exact, **TINY)
    assert bool(scene.poses_trusted) == trusted
    return scene
