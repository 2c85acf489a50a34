"""A run's set-up: which step plugins it has, in order (``train/plugins.py`` describes them)."""
from __future__ import annotations

from d2gs_np.train.config import ExperimentConfig
from d2gs_np.train.plugins import Densify, GradientStatistics, HeldOutPSNR, Prune
from d2gs_np.train.pose_solver import PoseSolver, use_pose_solver

__all__ = ["default_plugins"]


def default_plugins(scene, config: ExperimentConfig, extent: float, note=None, run_dir=None) -> list:
    """The plugins a run has by its config, in order (module docstring); the pose solver last,
    when ``train.pose_solver.use_pose_solver`` says so (its correspondence cache goes to ``run_dir``)."""
    tc = config.train
    plugins = []
    if tc.eval_every:
        plugins.append(HeldOutPSNR(scene, tc.eval_every, tc.eval_frames))
    if config.densify.enabled:
        plugins.append(GradientStatistics(config.densify.absgrad))
    if tc.prune_every:
        plugins.append(Prune(config, extent, [f.mask for f in scene.frames]))
    if config.densify.enabled:
        plugins.append(Densify(config, extent, max(f.width for f in scene.frames), note))
    if use_pose_solver(scene, config, note):
        plugins.append(PoseSolver(scene, config, run_dir, note))
    return plugins
