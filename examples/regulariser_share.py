"""How much each regulariser weighs in the loss and in the gradient, at the method's weights.

For a trained run (its final model) and every k-th training frame at full resolution: the value of
L_render and of lambda x each regulariser (docs/method.md §6), and the norm of each term's
gradient on the blocks it acts on, next to L_render's gradient on the same blocks (through the
render backward): L_freq on every scene block, L_gs on ``*.opacity_logits``, L_ts on
``dynamic.deform_*``. Means over the frames. This is how the λ_freq of docs/method.md §6 was
checked under the orthonormal-FFT / mean-over-bins normalisation. Also each term's forward +
backward time as a ratio to the frame's render forward + backward, timed in the same run.

    python examples/regulariser_share.py runs/ablation/runs/wall_disk_s0_render_only \
        runs/ablation/scenes/wall_disk_s0_blurry_true
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time

import numpy as np


def block_norm(grads, prefixes):
    return float(np.sqrt(sum(np.sum(v.astype(np.float64) ** 2) for n, v in grads.items() if n.startswith(prefixes))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("scene")
    ap.add_argument("--every", type=int, default=4, help="use every k-th frame (default 4)")
    args = ap.parse_args(argv)

    from d2gs_np.data.io import load_scene
    from d2gs_np.evaluation.runs import load_run
    from d2gs_np.train.config import METHOD_REGULARISER_WEIGHTS, LossConfig
    from d2gs_np.train.model import frame_render_bwd, frame_render_fwd
    from d2gs_np.train.terms import TermInputs, loss_terms

    model = load_run(args.run).model
    # the exact gradient of the render (every virtual view), not training's two-view estimate
    model = model.replace(config=model.config.replace(blur=dataclasses.replace(model.config.blur, backward_views=0)))
    scene = load_scene(args.scene)
    terms = {t.name: t for t in loss_terms(LossConfig(**METHOD_REGULARISER_WEIGHTS), model.components)}
    for t in terms.values():
        for p in getattr(t, "plugins", ()):
            p.on_init(model)
    joint = type("Stage", (), {"static_only": False, "name": "joint"})()
    scene_blocks = ("static.", "dynamic.")
    acting_on = {"freq": scene_blocks, "gs": ("static.opacity_logits", "dynamic.opacity_logits"),
                 "ts": ("dynamic.deform_",)}
    rows = {}
    for k in range(0, len(scene.frames), args.every):
        f = scene.frames[k]
        out, saved = frame_render_fwd(model, k, np.asarray(f.K, dtype=np.float64), f.width, f.height)
        x = TermInputs(out, f.image, None, model, k, joint)
        values, grads, times = {}, {}, {}
        t0 = time.perf_counter()
        _, sr = frame_render_fwd(model, k, np.asarray(f.K, dtype=np.float64), f.width, f.height)
        frame_render_bwd(sr, np.zeros_like(out["image"]))
        render_time = time.perf_counter() - t0
        for name, term in terms.items():
            t0 = time.perf_counter()
            value, s = term.fwd(x)
            g = term.bwd(s)
            seconds = time.perf_counter() - t0
            values[name] = term.weight * value
            times[name] = seconds
            if "image" in g.render:
                _, sr = frame_render_fwd(model, k, np.asarray(f.K, dtype=np.float64), f.width, f.height)
                grads[name] = frame_render_bwd(sr, g.render["image"])[0]
            else:
                grads[name] = g.params
        for name in terms:
            if name == "photometric":
                continue
            r = rows.setdefault(name, {"value": [], "render_value": [], "grad": [], "render_grad": [], "time": [],
                                       "render_time": []})
            r["value"].append(values[name])
            r["render_value"].append(values["photometric"])
            r["grad"].append(block_norm(grads[name], acting_on[name]))
            r["render_grad"].append(block_norm(grads["photometric"], acting_on[name]))
            r["time"].append(times[name])
            r["render_time"].append(render_time)
    print(f"run {args.run}, {len(range(0, len(scene.frames), args.every))} frames at full resolution, method weights")
    print("| term | lambda x value | L_render | value share | gradient norm | L_render's on the same blocks | ratio | "
          "fwd+bwd time / render fwd+bwd |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        m = {k: float(np.mean(v)) for k, v in r.items()}
        print(f"| {name} | {m['value']:.3g} | {m['render_value']:.3g} | {m['value'] / m['render_value']:.3f} | "
              f"{m['grad']:.3g} | {m['render_grad']:.3g} | {m['grad'] / m['render_grad']:.3f} | "
              f"{m['time'] / m['render_time']:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
