"""In-memory scene: frames, cameras, masks and optional ground truth.

All poses here are in the project's internal convention: ``cam_T_world``
(world-to-camera, OpenCV axes: x right, y down, z forward), 4x4 float64.
The on-disk format (``docs/dataset_format.md``) stores OpenGL
camera-to-world matrices; ``d2gs_np.data.io`` converts on load and save.
Images are float64 (H, W, 3) in [0, 1]; masks are bool (H, W), True = dynamic.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np


@dataclass
class Frame:
    file_path: str  # image path relative to the scene folder
    time: float  # normalised exposure-midpoint time in [0, 1]
    cam_T_world: np.ndarray  # (4, 4) the pose the method is given (estimate in training frames)
    K: np.ndarray  # (3, 3) pinhole intrinsics, zero skew
    width: int
    height: int
    image: Optional[np.ndarray] = None  # (H, W, 3) float64 in [0, 1]; None until loaded
    mask: Optional[np.ndarray] = None  # (H, W) bool, True = moving pixel
    mask_path: Optional[str] = None
    sharp: Optional[np.ndarray] = None  # (H, W, 3) ground-truth sharp mid-exposure image
    sharp_file_path: Optional[str] = None
    # (H, W) float64 true depth: camera z of the first surface through each pixel centre at the
    # frame's time and true pose; +inf where the ray hits nothing (geometry evaluation)
    depth: Optional[np.ndarray] = None
    depth_file_path: Optional[str] = None
    # (H, W) float64 estimated depth or disparity, known up to a scale and shift (e.g. a monocular
    # depth network's); NaN where there is no estimate. Seeds the dynamic set's depth
    # (InitConfig.dynamic_depth = "prior"); never used to score.
    depth_prior: Optional[np.ndarray] = None
    depth_prior_file_path: Optional[str] = None
    gt_cam_T_world: Optional[np.ndarray] = None  # (4, 4) true mid-exposure pose
    gt_exposure_start: Optional[np.ndarray] = None  # (4, 4) true cam_T_world at exposure start
    gt_exposure_end: Optional[np.ndarray] = None  # (4, 4) true cam_T_world at exposure end


@dataclass
class Scene:
    frames: list  # list[Frame], the (blurry) training video, in time order
    test_frames: list = field(default_factory=list)  # list[Frame]: true poses, test images
    exposure_fraction: Optional[float] = None  # exposure / frame interval, if known
    scene_scale: Optional[float] = None
    blur_subframes: Optional[int] = None
    root: Optional[Path] = None  # folder it was loaded from, if any
    poses_trusted: Optional[bool] = None  # True: the given poses are exact (no pose refinement)
    points3d: Optional[np.ndarray] = None  # (P, 3) sparse static world points (optional ply_file_path)
    points3d_colors: Optional[np.ndarray] = None  # (P, 3) their RGB in [0, 1]
    # what load_scene warned about (SceneWarning, one line each; docs/dataset_format.md §5)
    warnings: list = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def has_masks(self) -> bool:
        return all(f.mask is not None for f in self.frames)

    @property
    def frames_without_masks(self) -> list:
        """Indices of the frames that have no motion mask while others have one; [] when all or none do."""
        lacking = [i for i, f in enumerate(self.frames) if f.mask is None and f.mask_path is None]
        return lacking if len(lacking) < len(self.frames) else []

    @property
    def has_moving_pixels(self) -> bool:
        return self.has_masks and any(bool(np.any(f.mask)) for f in self.frames)

    @property
    def has_depth(self) -> bool:
        return bool(self.frames) and all(f.depth is not None for f in self.frames)

    @property
    def has_depth_prior(self) -> bool:
        return bool(self.frames) and all(f.depth_prior is not None for f in self.frames)

    @property
    def has_sharp(self) -> bool:
        return all(f.sharp is not None for f in self.frames)

    @property
    def has_gt_poses(self) -> bool:
        return all(f.gt_cam_T_world is not None for f in self.frames)
