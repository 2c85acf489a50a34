"""Crops of the largest mover, runs side by side (issue #44's pictures; docs/results.md §4).

Each argument is one scene's runs, comma-separated (the same scene folder). Per scene two rows,
cropped around the moving pixels as the report crops them (``reporting.html.mover_crop``):
the training frame where the movers cover most pixels, blurry input | each run's deblurred render
(its mid pose and time) | the sharp truth; and the test view where they cover most, each run's
render at the test pose carried through the evaluation's alignment (``d2gs eval``'s ``nvs``) | the
truth. Each crop's moving-pixel PSNR is printed. Needs scenes with sharp frames, motion masks and
true poses (the suite's).

    python examples/mover_crops.py RUN_A1,RUN_B1 [RUN_A2,RUN_B2 ...] --out crops.png
"""
from __future__ import annotations

import argparse

import numpy as np


def scene_crops(run_dirs, zoom=3):
    """(deblurred row, novel row, lines): lists of (h, w, 3) crops for one scene's runs, and the
    moving-pixel PSNR of each run's crop, as text."""
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation import metrics
    from d2gs_np.evaluation.runs import align_with_orientations, load_run
    from d2gs_np.reporting.html import mover_crop

    from d2gs_np.train.run_folder import check_scene_of_run

    runs = [load_run(r) for r in run_dirs]
    scene = load_scene(runs[0].meta["scene_root"])
    for path, run in zip(run_dirs[1:], runs[1:]):  # the same frames, wherever their folder is
        try:
            check_scene_of_run(run.meta, scene, path, "mover_crops", "give one scene's runs per argument")
        except ValueError as e:
            raise SystemExit(f"the runs of one argument must share a scene: {e}") from None
    if not scene.has_gt_poses or not scene.has_masks or not scene.test_frames:
        raise SystemExit(f"{run_dirs[0]}: its scene needs true poses, motion masks and test views")
    gt = np.stack([f.gt_cam_T_world for f in scene.frames])
    k = int(np.argmax([f.mask.sum() for f in scene.frames]))
    f = scene.frames[k]
    v_i = int(np.argmax([v.mask.sum() for v in scene.test_frames]))
    v = scene.test_frames[v_i]
    lines = [f"training frame {k}, test view {v_i}"]
    trained, novel = [], []
    for path, run in zip(run_dirs, runs):
        m = run.model
        im = m.render(m.mid_pose(k), f.time, f.K, f.width, f.height)
        to_ours = metrics.sim3_inverse(*align_with_orientations(m.mid_poses(), gt, scene.scene_scale))
        te = m.render(metrics.sim3_apply_to_poses(*to_ours, v.cam_T_world), v.time, v.K, v.width, v.height)
        lines.append(f"{path}: deblurred moving px {metrics.psnr(im, f.sharp, mask=f.mask):.2f} dB, "
                     f"novel view moving px {metrics.psnr(te, v.image, mask=v.mask):.2f} dB")
        trained.append(im)
        novel.append(te)
    row1, _ = mover_crop(f.mask, [f.image] + trained + [f.sharp], zoom=zoom)
    row2, _ = mover_crop(v.mask, novel + [v.image], zoom=zoom)
    return row1, row2, lines


def _strip(crops, height):
    import cv2

    out = [cv2.resize(np.clip(c, 0.0, 1.0), (max(1, round(c.shape[1] * height / c.shape[0])), height),
                      interpolation=cv2.INTER_NEAREST) for c in crops]
    gap = np.ones((height, 4, 3))
    return np.concatenate([x for c in out for x in (c, gap)][:-1], axis=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", help="per scene, its runs comma-separated")
    ap.add_argument("--out", required=True, help="the PNG to write")
    ap.add_argument("--height", type=int, default=160, help="each crop's height in the picture, px (default 160)")
    a = ap.parse_args(argv)
    if a.height < 8:
        ap.error(f"--height must be at least 8 px; got {a.height}")
    import cv2

    rows = []
    for spec in a.scenes:
        r1, r2, lines = scene_crops([s for s in spec.split(",") if s])
        if r1 is None or r2 is None:
            raise SystemExit(f"{spec}: nothing moves in its frames or test views")
        print("\n".join(lines))
        rows += [_strip(r1, a.height), _strip(r2, a.height)]
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 6), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    if not cv2.imwrite(a.out, (np.concatenate(rows, 0)[..., ::-1] * 255).round().astype(np.uint8)):
        raise SystemExit(f"could not write {a.out}")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
