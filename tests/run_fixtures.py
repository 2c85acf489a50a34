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


def step_and_checkpoint(trainer, steps):
    """Step ``trainer`` by hand to ``steps`` and checkpoint there (an interrupted run to resume)."""
    while trainer.step_index < steps:
        trainer.step(trainer.step_index)
        trainer.step_index += 1
    trainer.checkpoint()
    return trainer


TINY = dict(width=48, height=27, num_frames=6)  # a tiny clip of the "dynamic" preset: seconds to train


def tiny_dynamic_scene(trusted: bool, seed=0):
    """The "dynamic" preset at ``TINY`` size: true poses flagged as exact (``trusted``), or the
    preset's noisy ones."""
    from d2gs_np.data.synthetic import make_scene

    exact = dict(rot_noise_deg=0.0, trans_noise_fraction=0.0) if trusted else {}
    scene = make_scene("dynamic", seed, **exact, **TINY)
    assert bool(scene.poses_trusted) == trusted
    return scene


def expected_depth_descent(trainer, term_name, k=1):
    """A depth term's gradient through the render, checked by its directional derivative: the term
    ``term_name`` of ``trainer`` on frame ``k`` at full size, its cotangent on the expected depth
    through ``frame_render_bwd`` onto the static means g, and the central difference of the term
    along g at a mean step of at most 1e-7. Returns (value, slope, |g|^2, value after the step
    against g): the slope must match |g|^2, and the value must fall."""
    import numpy as np

    from d2gs_np.train.model import frame_render_bwd, frame_render_fwd
    from d2gs_np.train.terms import TermInputs

    term = next(t for t in trainer.terms if t.name == term_name)
    model = trainer.model
    tgt = trainer.cache.get(k, 1.0)

    def value(params):
        m = model.replace(params=params)
        out, saved = frame_render_fwd(m, k, tgt.K, tgt.width, tgt.height)
        return term.fwd(TermInputs(out, tgt.image, None, m, k, None)), saved

    (v, s), saved = value(model.params)
    assert s is not None, f"{term_name}: no valid pixel on frame {k}"
    grads = frame_render_bwd(saved, np.zeros_like(tgt.image), v_expected_depth=term.bwd(s).render["expected_depth"])[0]
    g = grads["static.means"]
    assert np.abs(g).max() > 0
    h = 1e-7 / np.abs(g).max()
    plus = dict(model.params, **{"static.means": model.params["static.means"] + h * g})
    minus = dict(model.params, **{"static.means": model.params["static.means"] - h * g})
    below = value(minus)[0][0]
    return v, (value(plus)[0][0] - below) / (2 * h), float(np.sum(g * g)), below
