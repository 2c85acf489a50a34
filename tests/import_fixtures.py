"""Helpers of the video import's tests (tests/video/): the suite's blurry clips and a folder of their frames."""
import functools

import cv2
import numpy as np

from d2gs_np.data.suite import build_suite_world, make_suite_scene, resolve

SMALL = dict(subframes=4, num_test_views=0)  # the suite size (240x135, 24 frames), cheaper blur
W, H = 240, 135


@functools.lru_cache(maxsize=None)
def suite_scene(preset):
    """The suite clip ``preset`` at seed 0 (cached per worker)."""
    return make_suite_scene(preset, 0, **SMALL)


def write_folder(scene, path):
    """The scene's blurry frames as PNGs in a new folder ``path``."""
    path.mkdir()
    for k, f in enumerate(scene.frames):
        cv2.imwrite(str(path / f"f{k:03d}.png"), np.round(f.image[:, :, ::-1] * 255).astype(np.uint8))
    return path


def depth(preset):
    """The scene depth of the suite clip ``preset`` (the unit of the ATE bounds)."""
    return build_suite_world(resolve(preset, 0, **SMALL)).depth
