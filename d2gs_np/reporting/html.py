"""A run's report as one self-contained HTML file (docs/method.md §10).

``write_report([RUN], OUT.html)`` writes what a researcher looks at first; with several runs
it puts them side by side (one metrics column, one picture row and one curve per run). The file
embeds every image as a base64 PNG, so it opens in any browser with no server and can be mailed.

Sections:
1. what the run modelled and what it left out, and why (the run log's notes);
2. metrics: deblurring view (DVS) PSNR/SSIM of the method beside the blurry inputs (and any
   other run given, e.g. the no-blur baseline), novel views, trajectory errors of the given and
   the refined poses (ATE, RPE), steps and seconds of training;
3. pictures: blurry input | deblurred render | sharp truth on a few frames, each with a zoomed
   crop of its most detailed region, and the novel views beside their truth; where the scene has
   true depth, each one's rendered depth | true depth | relative depth error (``depth_pictures``);
4. the camera trajectories (given, refined, true) seen from above, after the Sim(3) alignment
   of ATE;
5. error against wall-clock time: held-out PSNR (and ATE and held-out depth AbsRel, when the
   log records them) against seconds of training, every run on one plot.

Only what the run and its scene have is shown: a scene without sharp frames has no DVS row and
no truth column; one without true poses no trajectory errors or plot. Metrics come from
``RUN/metrics.json`` when present (``d2gs eval``), else are computed (``evaluate.evaluate_run``).
"""
from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from d2gs_np.base.checks import check_int
from d2gs_np.evaluation import metrics
from d2gs_np.data.io import load_scene
from d2gs_np.evaluation.runs import evaluate_run, load_run
from d2gs_np.geometry.camera import camera_center
from d2gs_np.reporting.plots import read_log

__all__ = ["write_report", "zoom_crop", "png_data_uri"]

_ZOOM = 3  # zoomed crops are shown at 3x, nearest neighbour (pixels stay visible)
_CROP_FRACTION = 0.25  # crop side as a fraction of the image's smaller side


def png_data_uri(image) -> str:
    """An (H, W, 3) float image in [0, 1] (or uint8) as a ``data:image/png;base64,`` URI."""
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = (np.clip(np.asarray(img, dtype=np.float64), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", img[..., ::-1] if img.ndim == 3 else img)
    if not ok:
        raise ValueError("could not encode the image as PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def _figure_uri(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def zoom_crop(reference, images, fraction=_CROP_FRACTION, zoom=_ZOOM):
    """The same square crop of each image, where ``reference`` (H, W, 3) has the most detail (the
    largest mean gradient magnitude over crop-sized windows on a coarse grid), enlarged ``zoom``
    times by pixel repetition. Returns (list of crops, (y0, x0, side))."""
    ref = np.asarray(reference, dtype=np.float64)
    h, w = ref.shape[:2]
    side = max(4, int(min(h, w) * fraction))
    gray = ref.mean(axis=2)
    gy, gx = np.gradient(gray)
    mag = np.hypot(gx, gy)
    best, where = -1.0, (0, 0)
    step = max(1, side // 2)
    for y in range(0, max(1, h - side + 1), step):
        for x in range(0, max(1, w - side + 1), step):
            s = float(mag[y:y + side, x:x + side].mean())
            if s > best:
                best, where = s, (y, x)
    y0, x0 = where
    crops = [np.repeat(np.repeat(np.asarray(im)[y0:y0 + side, x0:x0 + side], zoom, 0), zoom, 1) for im in images]
    return crops, (y0, x0, side)


def mover_crop(mask, images, pad=0.25, zoom=_ZOOM):
    """The same crop of each image around the moving pixels of ``mask`` (H, W) bool: their bounding
    box grown by ``pad`` of its size on every side (clipped to the image), enlarged ``zoom`` times
    by pixel repetition. Returns (list of crops, (y0, y1, x0, x1)); (None, None) when nothing moves."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return None, None
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    py = int(np.ceil(pad * (ys.max() - ys.min() + 1)))
    px = int(np.ceil(pad * (xs.max() - xs.min() + 1)))
    y0, y1 = max(0, ys.min() - py), min(h, ys.max() + 1 + py)
    x0, x1 = max(0, xs.min() - px), min(w, xs.max() + 1 + px)
    crops = [np.repeat(np.repeat(np.asarray(im)[y0:y1, x0:x1], zoom, 0), zoom, 1) for im in images]
    return crops, (int(y0), int(y1), int(x0), int(x1))


# ------------------------------------------------------------------ gathering a run
def _gather(run_dir, num_frames):
    run_dir = Path(run_dir)
    mpath = run_dir / "metrics.json"
    result = json.loads(mpath.read_text()) if mpath.exists() else evaluate_run(run_dir)
    run = load_run(run_dir)
    scene_dir = run.meta.get("scene_root")
    if scene_dir is None or not Path(scene_dir).exists():
        raise FileNotFoundError(f"the scene folder of run {run_dir} ({scene_dir}) is not there; the report needs it "
                                "for the input frames")
    scene = load_scene(scene_dir)
    model = run.model
    mids = model.mid_poses()
    ks = np.unique(np.linspace(0, scene.num_frames - 1, num_frames).round().astype(int))
    frames = []
    dscale = _get(result, "dvs", "depth", "scale") or 1.0  # our depths into the truth's units (evaluate)
    for k in ks:
        f = scene.frames[int(k)]
        out = model.render_outputs(mids[k], f.time, f.K, f.width, f.height)
        frames.append({"k": int(k), "input": f.image, "render": out["image"], "sharp": f.sharp,
                       "depth": dscale * out["expected_depth"], "true_depth": f.depth})
    mover = None
    areas = [0 if f.mask is None else int(np.count_nonzero(f.mask)) for f in scene.frames]
    if max(areas) > 0:  # the frame where the movers cover most pixels: blurry / ours / truth around them
        k = int(np.argmax(areas))
        f = scene.frames[k]
        mover = {"k": k, "mask": f.mask, "input": f.image, "sharp": f.sharp,
                 "render": model.render(mids[k], f.time, f.K, f.width, f.height)}
    novel = []
    if scene.test_frames and scene.has_gt_poses and len(scene.frames) >= 3:
        from d2gs_np.evaluation.runs import align_with_orientations

        gt = np.stack([f.gt_cam_T_world for f in scene.frames])
        s, R, t = metrics.sim3_inverse(*align_with_orientations(mids, gt, scene.scene_scale))
        for f in scene.test_frames[:2]:
            pose = metrics.sim3_apply_to_poses(s, R, t, f.cam_T_world)
            out = model.render_outputs(pose, f.time, f.K, f.width, f.height)
            novel.append({"render": out["image"], "truth": f.image, "depth": out["expected_depth"] / s,
                          "true_depth": f.depth})
    notes = []
    lpath = run_dir / "log.json"
    if lpath.exists():
        notes = json.loads(lpath.read_text()).get("notes", [])
    gt = np.stack([f.gt_cam_T_world for f in scene.frames]) if scene.has_gt_poses else None
    return {"dir": run_dir, "name": run_dir.name, "result": result, "frames": frames, "novel": novel, "mover": mover,
            "notes": notes, "poses_est": model.poses_est, "mids": mids, "gt": gt}


# ------------------------------------------------------------------ plots
def _trajectory_uri(runs):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6, 4.2))
    drawn_truth = False
    for r in runs:
        gt = r["gt"]
        if gt is None or len(gt) < 3:
            continue
        c_gt = camera_center(gt)
        # Top view: the two axes of largest spread of the true centres.
        spread = np.argsort(-np.var(c_gt, axis=0))[:2]
        for poses, style, label in ((r["poses_est"], "x--", "given"), (r["mids"], "o-", "refined")):
            try:
                s, R, t = metrics.align_trajectory(poses, gt)
            except ValueError:
                continue
            c = s * camera_center(poses) @ R.T + t
            ax.plot(c[:, spread[0]], c[:, spread[1]], style, ms=3, lw=1, label=f"{r['name']}: {label}")
        if not drawn_truth:
            ax.plot(c_gt[:, spread[0]], c_gt[:, spread[1]], "k-", lw=2, alpha=0.5, label="true")
            drawn_truth = True
    if not drawn_truth:
        plt.close(fig)
        return None
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("camera centres, top view (Sim(3)-aligned to the truth)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return _figure_uri(fig)


def _error_vs_time_uri(runs):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    logs = [(r["name"], read_log(r["dir"])) for r in runs if (Path(r["dir"]) / "log.csv").exists()]
    if not logs:
        return None
    has_ate = any("ate" in c and np.isfinite(c["ate"]).any() for _, c in logs)
    key = "heldout_depth_absrel"
    has_depth = any(key in c and np.isfinite(c[key]).any() for _, c in logs)
    panels = 1 + has_ate + has_depth
    fig, axes = plt.subplots(1, panels, figsize=(4.5 * panels + 1.5, 3.8), squeeze=False)
    ax = axes[0, 0]
    for name, c in logs:
        line, = ax.plot(c["seconds"], c["train_psnr"], alpha=0.3, lw=1)
        held = ~np.isnan(c["heldout_psnr"]) if "heldout_psnr" in c else np.zeros(len(c["seconds"]), bool)
        if held.any():
            ax.plot(c["seconds"][held], c["heldout_psnr"][held], "o-", ms=3, color=line.get_color(),
                    label=f"{name}: held-out vs sharp")
        ax.plot([], [], color=line.get_color(), alpha=0.3, label=f"{name}: train (vs its target)")
    ax.set_xlabel("training time [s]")
    ax.set_ylabel("PSNR [dB]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    if has_ate:
        ax = axes[0, 1]
        for name, c in logs:
            if "ate" in c:
                ok = np.isfinite(c["ate"])
                ax.plot(c["seconds"][ok], c["ate"][ok], "o-", ms=3, label=name)
        ax.set_xlabel("training time [s]")
        ax.set_ylabel("ATE")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if has_depth:
        ax = axes[0, panels - 1]
        for name, c in logs:
            if key in c:
                ok = np.isfinite(c[key])
                ax.plot(c["seconds"][ok], c[key][ok], "o-", ms=3, label=name)
        ax.set_xlabel("training time [s]")
        ax.set_ylabel("held-out depth AbsRel (given poses' units)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("error against wall-clock time (JIT warm-up and evaluation excluded)", fontsize=9)
    fig.tight_layout()
    return _figure_uri(fig)


# ------------------------------------------------------------------ HTML
def _fmt(x, spec=".2f"):
    return "&ndash;" if x is None else format(x, spec)


def _get(d, *keys):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


_METRIC_ROWS = (
    ("deblurred render vs sharp: PSNR [dB]", ("dvs", "psnr"), ".2f"),
    ("deblurred render vs sharp: SSIM", ("dvs", "ssim"), ".3f"),
    ("deblurred render vs sharp: FLIP (lower is better)", ("dvs", "flip"), ".4f"),
    ("blurry input vs sharp: PSNR [dB]", ("input_blur", "psnr"), ".2f"),
    ("blurry input vs sharp: SSIM", ("input_blur", "ssim"), ".3f"),
    ("blurry input vs sharp: FLIP (lower is better)", ("input_blur", "flip"), ".4f"),
    ("model re-blurred vs blurry input: PSNR [dB]", ("input_fit", "psnr"), ".2f"),
    ("sharpness: renders' gradient energy / inputs'", ("sharpness", "ratio"), ".2f"),
    ("moving pixels: blurry input vs sharp, PSNR [dB]", ("input_blur", "moving_psnr"), ".2f"),
    ("moving pixels: deblurred render vs sharp, PSNR [dB]", ("dvs", "moving_psnr"), ".2f"),
    ("static pixels: blurry input vs sharp, PSNR [dB]", ("input_blur", "static_psnr"), ".2f"),
    ("static pixels: deblurred render vs sharp, PSNR [dB]", ("dvs", "static_psnr"), ".2f"),
    ("novel views: PSNR [dB]", ("nvs", "psnr"), ".2f"),
    ("novel views, moving pixels: PSNR [dB]", ("nvs", "moving_psnr"), ".2f"),
    ("novel views, pixels some training frame saw: PSNR [dB]", ("nvs", "seen_psnr"), ".2f"),
    ("novel views, pixels no training frame saw: PSNR [dB]", ("nvs", "unseen_psnr"), ".2f"),
    ("novel views, share of pixels no training frame saw", ("nvs", "unseen_share"), ".3f"),
    ("novel views, each test view (time: PSNR [dB])", ("nvs", "views"), "views"),
    ("novel views: SSIM", ("nvs", "ssim"), ".3f"),
    ("novel views: FLIP (lower is better)", ("nvs", "flip"), ".4f"),
    ("novel views placed beside their frame's camera (DyBluRF's protocol): PSNR [dB]", ("nvs_rig", "psnr"), ".2f"),
    ("novel views beside their frame's camera, moving pixels: PSNR [dB]", ("nvs_rig", "moving_psnr"), ".2f"),
    ("novel views, test poses refined: PSNR [dB]", ("nvs_pose_opt", "psnr"), ".2f"),
    ("novel views, test poses refined, moving pixels: PSNR [dB]", ("nvs_pose_opt", "moving_psnr"), ".2f"),
    ("depth AbsRel, deblurred views (lower is better)", ("dvs", "depth", "absrel"), ".4f"),
    ("depth AbsRel, deblurred views, static pixels", ("dvs", "depth", "absrel_static"), ".4f"),
    ("depth AbsRel, deblurred views, moving pixels", ("dvs", "depth", "absrel_moving"), ".4f"),
    ("depth delta < 1.25, deblurred views", ("dvs", "depth", "delta1"), ".3f"),
    ("depth AbsRel, novel views", ("nvs", "depth", "absrel"), ".4f"),
    ("depth delta < 1.25, novel views", ("nvs", "depth", "delta1"), ".3f"),
    ("ATE, given poses", ("trajectory", "initial", "ate"), ".4f"),
    ("ATE, given poses after bundle adjustment (start of training)", ("trajectory", "bundle_adjusted", "ate"), ".4f"),
    ("ATE, refined poses", ("trajectory", "ate"), ".4f"),
    ("ATE alignment scale, given -> refined (1 = kept its size)", None, None),
    ("RPE_t, given -> refined", None, None),
    ("RPE_r [deg], given -> refined", None, None),
    ("training steps", ("steps",), "d"),
    ("training seconds", ("train_seconds",), ".1f"),
)


def _metrics_table(runs):
    head = "".join(f"<th>{html.escape(r['name'])}</th>" for r in runs)
    rows = []
    for label, keys, spec in _METRIC_ROWS:
        cells = []
        for r in runs:
            m = r["result"]
            if keys is None:
                key = "rpe_t" if "RPE_t" in label else "rpe_r" if "RPE_r" in label else "scale"
                a, b = _get(m, "trajectory", "initial", key), _get(m, "trajectory", key)
                cells.append(f"{_fmt(a, '.4f')} &rarr; {_fmt(b, '.4f')}")
            elif spec == "views":
                views = _get(m, *keys)
                cells.append("<br>".join(f"{v['time']:.2f}: {_fmt(v.get('psnr'), '.2f')}" for v in views)
                             if views else "&ndash;")
            else:
                cells.append(_fmt(_get(m, *keys), spec))
        if any(c not in ("&ndash;", "&ndash; &rarr; &ndash;") for c in cells):
            rows.append(f"<tr><td>{label}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    return f"<table><tr><th></th>{head}</tr>{''.join(rows)}</table>"


def _verdicts(runs):
    """Each run's ``evaluation.runs.verdict`` lines; a run without the blur model among them is the
    baseline of the others. A loss to the input or to the baseline is marked."""
    from d2gs_np.evaluation.runs import verdict

    base = next((r["result"] for r in runs if "blur_model" in r["result"].get("left_out", [])), None)
    parts = []
    for r in runs:
        lines = verdict(r["result"], None if r["result"] is base else base)
        for line in lines:
            lost = "LOST" in line
            attr, mark = (' class="lost"', "&#9888; ") if lost else ("", "")
            parts.append(f"<p{attr}><b>{html.escape(r['name'])}</b>: {mark}{html.escape(line)}</p>")
    return "".join(parts)


def depth_pictures(depth, true_depth, max_rel=0.5):
    """(rendered, true, error) RGB images of a depth map and its truth: inverse depth on one
    colour scale (the truth's range; black where there is no surface), and |d - d*| / d* from 0
    to ``max_rel`` (and above)."""
    import matplotlib

    t = np.asarray(true_depth, dtype=np.float64)
    d = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(t) & (t > 0)
    lo, hi = (np.min(1.0 / t[ok]), np.max(1.0 / t[ok])) if ok.any() else (0.0, 1.0)
    cmap = matplotlib.colormaps["viridis"]

    def inv(x):
        good = np.isfinite(x) & (x > 0)
        v = np.where(good, 1.0 / np.where(good, x, 1.0), 0.0)
        img = cmap(np.clip((v - lo) / max(hi - lo, 1e-12), 0.0, 1.0))[..., :3]
        img[~good] = 0.0
        return img
    rel = np.where(ok, np.abs(np.where(np.isfinite(d), d, 0.0) - np.where(ok, t, 1.0)) / np.where(ok, t, 1.0), 0.0)
    err = matplotlib.colormaps["magma"](np.clip(rel / max_rel, 0.0, 1.0))[..., :3]
    err[~ok] = 0.0
    return inv(d), inv(t), err


def _depth_row(item, what):
    if item.get("true_depth") is None:
        return ""
    ims = depth_pictures(item["depth"], item["true_depth"])
    absrel = metrics.depth_errors(item["depth"], item["true_depth"])["absrel"]
    names = (f"{what}: rendered depth (AbsRel {_fmt(absrel, '.4f')})", f"{what}: true depth",
             f"{what}: |depth error| / depth, 0 to 0.5")
    return '<div class="row">' + "".join(_img(png_data_uri(im), n) for im, n in zip(ims, names)) + "</div>"


def _img(uri, title=""):
    return f'<figure><img src="{uri}"><figcaption>{html.escape(title)}</figcaption></figure>'


def _pictures(r):
    parts = []
    for f in r["frames"]:
        ims = [f["input"], f["render"]] + ([f["sharp"]] if f["sharp"] is not None else [])
        names = ["blurry input", "deblurred render", "sharp truth"][:len(ims)]
        scores = [""] * len(ims)
        if f["sharp"] is not None:
            scores[0] = f" ({metrics.psnr(f['input'], f['sharp']):.2f} dB)"
            scores[1] = f" ({metrics.psnr(f['render'], f['sharp']):.2f} dB)"
        crops, (y0, x0, side) = zoom_crop(f["sharp"] if f["sharp"] is not None else f["input"], ims)
        row = "".join(_img(png_data_uri(im), f"frame {f['k']}: {n}{s}") for im, n, s in zip(ims, names, scores))
        row += "".join(_img(png_data_uri(c), f"zoom x{_ZOOM} at ({x0}, {y0}), {side} px: {n}")
                       for c, n in zip(crops, names))
        parts.append(f'<div class="row">{row}</div>')
        parts.append(_depth_row(f, f"frame {f['k']}"))
    m = r.get("mover")
    if m is not None:
        ims = [m["input"], m["render"]] + ([m["sharp"]] if m["sharp"] is not None else [])
        names = ["blurry input", "deblurred render", "sharp truth"][:len(ims)]
        scores = [""] * len(ims)
        if m["sharp"] is not None:
            scores[:2] = [f", moving pixels {metrics.psnr(im, m['sharp'], mask=m['mask']):.2f} dB" for im in ims[:2]]
        crops, (y0, y1, x0, x1) = mover_crop(m["mask"], ims)
        parts.append('<div class="row">' + "".join(
            _img(png_data_uri(c), f"largest mover, frame {m['k']}, rows {y0}-{y1}, columns {x0}-{x1}: {n}{sc}")
            for c, n, sc in zip(crops, names, scores)) + "</div>")
    for i, nv in enumerate(r["novel"]):
        p = metrics.psnr(nv["render"], nv["truth"])
        parts.append('<div class="row">' + _img(png_data_uri(nv["render"]), f"novel view {i}: render ({p:.2f} dB)")
                     + _img(png_data_uri(nv["truth"]), f"novel view {i}: truth") + "</div>")
        parts.append(_depth_row(nv, f"novel view {i}"))
    return "".join(parts)


_CSS = """body{font-family:sans-serif;margin:1.5em;max-width:1400px}table{border-collapse:collapse;margin:1em 0}
td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}td:first-child{text-align:left}
.row{display:flex;flex-wrap:wrap;gap:6px;margin-bottom:10px}figure{margin:0}figcaption{font-size:11px;color:#333}
img{image-rendering:pixelated;max-width:100%}ul{font-size:13px}.lost{color:#b00000}"""


def write_report(run_dirs, out_html, num_frames: int = 3, title: str = "d2gs_np report") -> Path:
    """Write the report of one run, or several side by side, to ``out_html`` (module docstring)."""
    run_dirs = [run_dirs] if isinstance(run_dirs, (str, Path)) else list(run_dirs)
    if not run_dirs:
        raise ValueError("write_report needs at least one run folder")
    check_int(num_frames, "num_frames", 1)
    for d in run_dirs:
        if not (Path(d) / "final.npz").exists() and not (Path(d) / "checkpoint.npz").exists():
            raise FileNotFoundError(f"{d} is not a training run (no final.npz or checkpoint.npz); train it first "
                                    f"(d2gs train SCENE --out {d})")
    runs = [_gather(d, num_frames) for d in run_dirs]
    body = [f"<h1>{html.escape(title)}</h1>"]
    body.append("<h2>What each run modelled</h2>")
    for r in runs:
        left = r["result"].get("left_out", [])
        body.append(f"<h3>{html.escape(r['name'])}</h3><p>left out: {html.escape(', '.join(left) or 'nothing')}</p>")
        body.append("<ul>" + "".join(f"<li>{html.escape(str(n))}</li>" for n in r["notes"]) + "</ul>")
    said = _verdicts(runs)
    if said:
        body.append("<h2>What the numbers say</h2>" + said)
    body.append("<h2>Metrics</h2>" + _metrics_table(runs))
    curve = _error_vs_time_uri(runs)
    if curve:
        body.append("<h2>Error against wall-clock time</h2>" + _img(curve))
    traj = _trajectory_uri(runs)
    if traj:
        body.append("<h2>Camera trajectories</h2>" + _img(traj))
    body.append("<h2>Pictures</h2>")
    for r in runs:
        body.append(f"<h3>{html.escape(r['name'])}</h3>" + _pictures(r))
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style></head><body>{''.join(body)}</body></html>\n")
    out = Path(out_html)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(page)
    tmp.replace(out)  # atomic: a reader never sees half a report
    return out
