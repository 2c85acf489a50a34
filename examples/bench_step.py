"""Fixed-seed training run: final metrics to the last bit, and the mean time of a training step.

Trains a tiny synthetic scene (the ``dynamic`` preset: moving spheres, hand-shake blur, noisy
poses) with every component on (dynamic set, blur model with n = 8, progressive resolution,
pruning, densification, held-out evaluation, a checkpoint), then evaluates the run. It prints:

- the final metrics (``evaluate``, without the wall-clock entries), the last log row, the
  held-out PSNRs with ``repr``, a SHA-256 of the logged losses and one of every final parameter
  block: two runs of the same code, or of two versions that claim identical numerics, must
  print the same lines (all but the timings);
- the mean and median seconds per training step, read from the run log (training time only:
  JIT warm-up, evaluation and checkpointing are excluded by the trainer's stopwatch), without
  the first ``--skip`` steps.

Compare step times only between runs under the same conditions (threads, machine load):

    NUMBA_NUM_THREADS=1 python examples/bench_step.py [--iters 60] [--out /tmp/bench_step]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from d2gs_np.data.synthetic import make_scene
from d2gs_np.evaluation.runs import evaluate, load_run
from d2gs_np.train.checkpoint import load_checkpoint
from d2gs_np.train.config import ExperimentConfig, TrainConfig
from d2gs_np.train.config import DensifyConfig
from d2gs_np.train.trainer import Trainer

SCENE = dict(width=64, height=36, num_frames=8)


def config(iters: int) -> ExperimentConfig:
    """Every component on, housekeeping often enough to run several times in a short run."""
    train = TrainConfig(iters=iters, seed=0, quiet=True, log_every=1, eval_every=20, checkpoint_every=25,
                        prune_every=20, prune_opacity=0.02)
    dens = DensifyConfig(enabled=True, every=10, start_fraction=0.1, stop_fraction=0.8, grad_threshold_ndc=2e-4)
    return ExperimentConfig(train=train, densify=dens)


def digest(params: dict) -> str:
    h = hashlib.sha256()
    for name in sorted(params):
        a = np.ascontiguousarray(params[name])
        h.update(name.encode())
        h.update(str(a.dtype).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iters", type=int, default=60)
    ap.add_argument("--skip", type=int, default=2, help="steps left out of the timing (first-call overheads)")
    ap.add_argument("--out", default=None, help="run folder (default: a temporary one, removed)")
    args = ap.parse_args(argv)
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_step_"))
    try:
        scene = make_scene("dynamic", 0, **SCENE)
        t0 = time.perf_counter()
        trainer = Trainer(scene, config(args.iters), out / "run", overwrite=True)
        t_init = time.perf_counter() - t0
        result = trainer.run()
        run = load_run(out / "run")
        metrics = evaluate(run, scene)
        for wall in ("train_seconds",):
            metrics.pop(wall, None)
        rows = json.loads((out / "run" / "log.json").read_text())["rows"]
        # The columns every version logs (a version may add per-loss-term columns); seconds vary.
        last = {k: rows[-1].get(k) for k in ("step", "stage", "loss", "train_psnr", "heldout_psnr", "scale",
                                              "num_gaussians")}
        print("metrics", repr(metrics))
        print("last_row", repr(last))
        print("heldout", repr([(r["step"], r["heldout_psnr"]) for r in rows if r["heldout_psnr"] is not None]))
        print("losses_sha256", hashlib.sha256(repr([r["loss"] for r in rows]).encode()).hexdigest())
        arrays, _ = load_checkpoint(out / "run" / "final.npz")
        print("params_sha256", digest({k[len("params/"):]: v for k, v in arrays.items() if k.startswith("params/")}))
        print("num_gaussians", repr(int(rows[-1]["num_gaussians"])), "steps", repr(result.steps))
        secs = [r["seconds"] for r in rows]
        per_step = np.diff([0.0] + secs)[args.skip:]
        print(f"init_seconds {t_init:.3f}")
        print(f"step_seconds mean {float(np.mean(per_step)):.5f} median {statistics.median(per_step):.5f} "
              f"over {len(per_step)} steps; train_seconds {result.train_seconds:.3f}")
    finally:
        if not args.out:
            shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
