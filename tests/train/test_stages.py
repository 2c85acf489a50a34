"""Tests of the step planner's frame order (d2gs_np/train/stages.py)."""
from __future__ import annotations

from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.stages import Planner, make_stages


def _planner(num_frames=6, seed=0):
    cfg = ExperimentConfig(train=TrainConfig(iters=100, seed=seed))
    return Planner(cfg, [(32, 24)] * num_frames, make_stages(cfg.train, False))


def test_frame_order_visits_every_frame_once_per_epoch_and_depends_only_on_seed_and_step():
    p = _planner()
    for epoch in range(5):
        assert sorted(p.frame_for_step(epoch * 6 + i) for i in range(6)) == list(range(6))
    order = [p.frame_for_step(s) for s in range(30)]
    assert [_planner().frame_for_step(s) for s in range(30)] == order  # a new planner (a resume) agrees
    assert [_planner(seed=1).frame_for_step(s) for s in range(30)] != order
    assert order[:6] != order[6:12]  # a new permutation each epoch


def test_camera_from_leaves_the_camera_out_of_the_first_steps_only():
    def trains_camera(stage):
        return any(p.startswith(("camera.", "posenet.")) for p in stage.trainable)

    for dynamic in (False, True):
        base = make_stages(TrainConfig(iters=100), dynamic)
        stages = make_stages(TrainConfig(iters=100, camera_from_fraction=0.3), dynamic)
        assert stages[0].start == 0 and stages[-1].stop == 100
        assert all(a.stop == b.start for a, b in zip(stages, stages[1:]))  # contiguous, no step lost
        for step in range(100):
            new = next(s for s in stages if s.start <= step < s.stop)
            old = next(s for s in base if s.start <= step < s.stop)
            gaussians = {p for p in old.trainable if not p.startswith(("camera.", "posenet."))}
            assert set(new.trainable) >= gaussians and new.static_only == old.static_only
            assert trains_camera(new) == (step >= 30 and trains_camera(old)), step
    assert make_stages(TrainConfig(iters=100, camera_from_fraction=0.0), True) == make_stages(TrainConfig(iters=100), True)
