"""Benchmark: load a 24-frame 240x135 scene folder (masks and sharp images included).

Run: python examples/bench_io.py
Writes a random scene to a temporary folder, then times ``load_scene`` (median
of several runs, warm file cache) with and without pixel decoding.
"""
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from d2gs_np.data.io import load_scene, write_scene
from d2gs_np.data.scene import Frame, Scene
from d2gs_np.geometry.camera import make_intrinsics

N_FRAMES, W, H, REPEATS = 24, 240, 135, 7


def make_scene(rng):
    frames = []
    for i in range(N_FRAMES):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        T[:3, 3] = rng.standard_normal(3)
        frames.append(Frame(
            file_path=f"images/{i:04d}.png", time=i / (N_FRAMES - 1), cam_T_world=T,
            K=make_intrinsics(200.0, 200.0, W / 2, H / 2), width=W, height=H,
            image=rng.random((H, W, 3)), mask=rng.random((H, W)) < 0.2, mask_path=f"masks/{i:04d}.png",
            sharp=rng.random((H, W, 3)), sharp_file_path=f"sharp/{i:04d}.png", gt_cam_T_world=T.copy(),
        ))
    return Scene(frames=frames, exposure_fraction=0.5, blur_subframes=9)


def median_time(fn):
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main():
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "scene"
        t0 = time.perf_counter()
        write_scene(make_scene(rng), root)
        t_write = time.perf_counter() - t0
        load_scene(root)  # warm the file cache
        t_full = median_time(lambda: load_scene(root))
        t_meta = median_time(lambda: load_scene(root, load_images=False))
    print(f"scene: {N_FRAMES} frames {W}x{H}, masks + sharp images (72 PNGs), median of {REPEATS}")
    print(f"write_scene                     {t_write * 1e3:8.1f} ms (single run)")
    print(f"load_scene                      {t_full * 1e3:8.1f} ms")
    print(f"load_scene(load_images=False)   {t_meta * 1e3:8.1f} ms")


if __name__ == "__main__":
    main()
