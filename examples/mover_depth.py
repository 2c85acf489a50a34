"""How far a run's movers land off in its novel views, from their depth (docs/results.md §4, "Position
steps by depth", session 44).

For each test view and the training frame of its time: the ratio of the model's rendered (expected)
depth to the true depth on the frame's moving pixels (median and 10th / 90th percentiles) and on
its static pixels (median: a mover placed right against the static world sits at that), the
mover's parallax between the frame's camera and the test view (focal length x baseline / the
mover's median true depth, px), and what the ratios move the mover's pixels by in the test view:
the median's shift, parallax x |1 - 1 / median ratio|, and the spread between the 10th and 90th
percentiles, parallax x |1 / p10 - 1 / p90|. A mover rendered as a sharp picture in the training
view lands smeared by that spread in the novel view. Then the test view itself, rendered at its pose
carried through the evaluation's alignment (``d2gs eval``'s ``nvs``): the PSNR of its moving pixels,
and the whole-pixel shift of the render (within ``--radius`` px) that scores them best, with that
score: how much of the moving pixels' loss is where they land rather than what they look like. Needs a scene with true depth, motion masks and
test views at training frames' times (the suite's).

    python examples/mover_depth.py RUN [RUN ...] [--radius 4]
"""
from __future__ import annotations

import argparse

import numpy as np


def depth_ratios(expected_depth, true_depth, mask):
    """(median, p10, p90) of expected / true depth over ``mask`` pixels with positive true depth."""
    e, t, m = (np.asarray(a) for a in (expected_depth, true_depth, mask))
    if e.shape != t.shape or m.shape != t.shape:
        raise ValueError(f"depth maps and mask must share a shape; got {e.shape}, {t.shape}, {m.shape}")
    keep = m.astype(bool) & (t > 0) & np.isfinite(e)
    if not keep.any():
        raise ValueError("no moving pixel with a true depth: nothing to measure")
    r = e[keep] / t[keep]
    return float(np.median(r)), float(np.percentile(r, 10)), float(np.percentile(r, 90))


def parallax_px(focal_px: float, baseline: float, depth: float) -> float:
    """Image shift (px) of a point at ``depth`` between two cameras ``baseline`` apart sideways."""
    if not depth > 0:
        raise ValueError(f"depth must be positive; got {depth}")
    return float(focal_px) * float(baseline) / float(depth)


def landing(parallax: float, ratios) -> tuple:
    """(shift of the median, spread p10-p90) in px that depth ratios (median, p10, p90) give a
    mover of ``parallax`` px: a point rendered at ratio r x its depth moves parallax x (1 - 1/r)."""
    med, lo, hi = ratios
    return parallax * abs(1.0 - 1.0 / med), parallax * abs(1.0 / lo - 1.0 / hi)


def best_shift(render, truth, mask, radius: int = 4):
    """(PSNR at no shift, the best PSNR, (dy, dx)) over the ``mask`` pixels of ``truth`` (h, w, c)
    against ``render`` moved by whole pixels, dy and dx in [-radius, radius]: the render's pixel
    (i - dy, j - dx) scored at (i, j), the mask pixels whose source leaves the image not counted."""
    from d2gs_np.evaluation import metrics

    a, b, m = (np.asarray(x) for x in (render, truth, mask))
    if a.shape != b.shape or a.ndim != 3 or m.shape != a.shape[:2]:
        raise ValueError(f"render and truth must be (h, w, c) and the mask (h, w); got {a.shape}, {b.shape}, {m.shape}")
    if not isinstance(radius, (int, np.integer)) or radius < 0:
        raise ValueError(f"radius must be a whole number of pixels >= 0; got {radius!r}")
    i, j = np.nonzero(m.astype(bool))
    if len(i) == 0:
        raise ValueError("no moving pixel: nothing to score")
    h, w = m.shape

    def psnr(dy, dx):
        si, sj = i - dy, j - dx
        keep = (si >= 0) & (si < h) & (sj >= 0) & (sj < w)
        if not keep.any():
            return -np.inf
        # the kept pixels as a one-row image, so the project's PSNR (its +inf when equal) scores them
        return float(metrics.psnr(a[si[keep], sj[keep]][None], b[i[keep], j[keep]][None]))
    scores = {(dy, dx): psnr(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)}
    top = max(scores, key=lambda k: (scores[k], -abs(k[0]) - abs(k[1])))
    return scores[(0, 0)], scores[top], top


def report(run_dir, radius: int = 4) -> str:
    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation import metrics
    from d2gs_np.evaluation.runs import align_with_orientations, frame_of_views, load_run

    run = load_run(run_dir)
    scene = load_scene(run.meta["scene_root"])
    frames = frame_of_views(scene)
    if not scene.has_gt_poses or frames is None:
        raise SystemExit(f"{run_dir}: its scene has no true poses, or a test view at no training frame's time")
    m = run.model
    gt = np.stack([f.gt_cam_T_world for f in scene.frames])
    # our depths in the truth's units: the alignment's scale maps our frame onto the truth's
    fit = align_with_orientations(m.mid_poses(), gt, scene.scene_scale)
    scale = fit[0]
    to_ours = metrics.sim3_inverse(*fit)  # carries the test poses into our frame, as d2gs eval does
    lines = [f"## {run_dir}", "",
             "| view | frame | depth ratio: median (p10, p90) | static px' depth ratio | parallax px | shift of the median px "
             "| spread px | test view moving px dB | best shift (dy, dx) px | its dB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for i, (v, k) in enumerate(zip(scene.test_frames, frames)):
        f = scene.frames[k]
        if f.mask is None or f.depth is None or not f.mask.any():
            lines.append(f"| {i} | {k} | no moving pixels or no true depth | | | | | | | |")
            continue
        o = m.render_outputs(m.mid_pose(k), f.time, f.K, f.width, f.height)
        ratios = depth_ratios(o["expected_depth"] * scale, f.depth, f.mask)
        # the static world's own ratio in the same frame: a mover placed right against the world sits at it
        static = depth_ratios(o["expected_depth"] * scale, f.depth, ~f.mask.astype(bool))[0]
        rel = v.cam_T_world @ np.linalg.inv(gt[k])
        par = parallax_px(f.K[0, 0], np.linalg.norm(rel[:3, 3]), float(np.median(f.depth[f.mask.astype(bool)])))
        shift, spread = landing(par, ratios)
        cells = "no moving pixels in the test view | |"
        if v.mask is not None and v.mask.any():
            te = m.render(metrics.sim3_apply_to_poses(*to_ours, v.cam_T_world), v.time, v.K, v.width, v.height)
            at0, top, (dy, dx) = best_shift(te, v.image, v.mask, radius)
            cells = f"{at0:.2f} | ({dy:+d}, {dx:+d}) | {top:.2f}"
        lines.append(f"| {i} | {k} | {ratios[0]:.3f} ({ratios[1]:.3f}, {ratios[2]:.3f}) | {static:.3f} | {par:.1f} | "
                     f"{shift:.2f} | {spread:.2f} | {cells} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="run folders of scenes with true depth, masks and test views")
    ap.add_argument("--radius", type=int, default=4, help="largest whole-pixel shift searched (default 4)")
    args = ap.parse_args(argv)
    for r in args.runs:
        print(report(r, args.radius))
        print()


if __name__ == "__main__":
    main()
