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
