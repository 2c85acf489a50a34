"""Novel views of evaluated runs under each protocol side by side (docs/method.md §10): the test
poses through the global similarity (`nvs`), placed beside the camera of their frame (`nvs_rig`,
DyBluRF's protocol) and refined on the frozen scene (`nvs_pose_opt`, when `d2gs eval RUN
--test-pose-opt N` wrote it), each on all, moving and seen pixels, with the deblurred views and the
static depth error beside. Reads each RUN/metrics.json; evaluates nothing.

    python examples/nvs_protocols.py RUN [RUN ...] [--labels A B ...]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def _get(m, *keys):
    for k in keys:
        if not isinstance(m, dict) or k not in m:
            return None
        m = m[k]
    return m


def _f(x, spec=".2f"):
    return "–" if x is None else format(x, spec)


def row(label, m) -> str:
    """One markdown row of a run's metrics (``metrics.json`` as a dict)."""
    cols = [_get(m, "dvs", "psnr"), _get(m, "dvs", "moving_psnr")]
    for key in ("nvs", "nvs_rig", "nvs_pose_opt"):
        cols += [_get(m, key, "psnr"), _get(m, key, "moving_psnr")]
    cols += [_get(m, "nvs", "seen_psnr"), _get(m, "nvs_rig", "seen_psnr")]
    cells = [_f(c) for c in cols] + [_f(_get(m, "dvs", "depth", "absrel_static"), ".3f"),
                                     _f(_get(m, "trajectory", "ate"), ".4f"), _f(_get(m, "steps"), "d")]
    return f"| {label} | " + " | ".join(cells) + " |"


HEADER = ("| run | DVS dB | DVS moving px | NVS aligned dB | moving px | NVS beside its frame dB | moving px | "
          "NVS test poses refined dB | moving px | seen px: aligned | seen px: beside its frame | "
          "static depth AbsRel | ATE | steps |\n" + "|---" * 14 + "|")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="evaluated run folders (RUN/metrics.json)")
    ap.add_argument("--labels", nargs="+", help="a label per run (default: the folder names)")
    args = ap.parse_args(argv)
    if args.labels and len(args.labels) != len(args.runs):
        ap.error(f"--labels takes one label per run: {len(args.runs)} runs, {len(args.labels)} labels")
    lines = [HEADER]
    for k, run in enumerate(args.runs):
        path = Path(run) / "metrics.json"
        if not path.exists():
            raise SystemExit(f"{path} does not exist; evaluate first (d2gs eval {run})")
        lines.append(row(args.labels[k] if args.labels else Path(run).name, json.loads(path.read_text())))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
