"""The ``d2gs refcheck`` subcommand: export, compare, run, gsplat (docs/refcheck.md §1).

Registered by ``d2gs_np.cli.build_parser`` through ``add_refcheck_parser``. A comparison that
runs and fails raises ``CheckFailed`` (exit status 1); usage errors exit 2.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["add_refcheck_parser", "CheckFailed"]


class CheckFailed(Exception):
    """A check ran and failed (``d2gs refcheck compare``): exit status 1, unlike a usage error's 2."""


def _cmd_refcheck_export(args):
    from d2gs_np.refcheck import export
    from d2gs_np.train.checkpoint import check_output_path

    check_output_path(args.dir, "export folder")
    entries = export(args.dir, cases=args.cases, dtype=args.dtype)
    print(f"wrote {len(entries)} cases and cases.json to {args.dir} (format: docs/refcheck.md)")


def _cmd_refcheck_run(args):
    from d2gs_np.refcheck import run
    from d2gs_np.train.checkpoint import check_output_path

    check_output_path(args.out, "output folder")
    run(args.dir, args.out, renderer=args.renderer, dtype=args.dtype, cases=args.cases)
    print(f"wrote our results for {args.dir} to {args.out}; check them with 'd2gs refcheck compare "
          f"{args.dir} {args.out}'")


def _cmd_refcheck_compare(args):
    from d2gs_np.refcheck import compare_dirs, format_table, parse_rtol

    rows, ok = compare_dirs(args.dir, args.theirs, rtol=parse_rtol(args.rtol), cases=args.cases,
                            tolerances=args.tolerances)
    print(format_table(rows))
    if not ok:
        raise CheckFailed("refcheck compare: some quantities differ beyond their tolerance (see the table)")


def _cmd_refcheck_gsplat(args):
    from d2gs_np.refcheck import compare_dirs, format_table, parse_rtol
    from d2gs_np.refcheck.gsplat_runner import GsplatUnavailable, run_gsplat

    from d2gs_np.train.checkpoint import check_output_path

    out = args.out if args.out else str(Path(args.dir) / "gsplat")
    check_output_path(out, "--out" if args.out else "output folder")
    try:
        covered = run_gsplat(args.dir, out, cases=args.cases, dtype=args.dtype)
    except GsplatUnavailable as e:
        raise ValueError(str(e)) from None
    rows, ok = compare_dirs(args.dir, out, rtol=parse_rtol(args.rtol), cases=covered,
                            tolerances="float32" if args.dtype == "float32" else None)
    print(format_table(rows))
    if not ok:
        raise CheckFailed("refcheck gsplat: gsplat's reference differs beyond the tolerances (see the table)")


def add_refcheck_parser(sub):
    """Add ``refcheck`` and its actions to the top-level subparsers ``sub``."""
    rc = sub.add_parser("refcheck", help="golden cases and a comparison for faster implementations "
                        "(docs/refcheck.md)",
                        description="Reference-check kit for faster (GPU, JAX, ...) splatting and deblurring "
                                    "implementations: export golden cases with every gradient, compare another "
                                    "implementation's results. File format, cases and tolerances: "
                                    "docs/refcheck.md; renderer conventions: docs/conventions.md.")
    rcs = rc.add_subparsers(dest="refcheck_command", required=True, metavar="ACTION")
    cases_help = "only these cases (default: all; see docs/refcheck.md §2)"
    ex = rcs.add_parser("export", help="write the golden cases (docs/refcheck.md §2-3)",
                        description="Write NAME.npz per case and cases.json to DIR: inputs in gsplat's layout, the "
                                    "upstream gradient, our outputs and gradients (docs/refcheck.md §2-3).")
    ex.add_argument("dir")
    ex.add_argument("--cases", nargs="+", default=None, help=cases_help)
    ex.add_argument("--dtype", choices=["float64", "float32"], default="float64",
                    help="dtype of the stored inputs and the tolerances (our results are float64 either way)")
    ex.set_defaults(func=_cmd_refcheck_export)
    cp = rcs.add_parser("compare", help="compare another implementation's results (docs/refcheck.md §5)",
                        description="Compare THEIRS_DIR (same file layout: out.* and grad.* per case) against the "
                                    "golden cases in DIR; prints a table and exits 1 on any failure "
                                    "(docs/refcheck.md §5).")
    cp.add_argument("dir")
    cp.add_argument("theirs")
    cp.add_argument("--rtol", nargs="+", default=None,
                    help="NUMBER (every quantity) and/or QUANTITY=NUMBER (e.g. grad.viewmats=1e-8) overriding the "
                         "documented tolerances")
    cp.add_argument("--tolerances", choices=["float64", "float32"], default=None,
                    help="default tolerance set (default: the export's dtype)")
    cp.add_argument("--cases", nargs="+", default=None, help=cases_help)
    cp.set_defaults(func=_cmd_refcheck_compare)
    rn = rcs.add_parser("run", help="evaluate an export with our own code, as a port would "
                        "(docs/refcheck.md §6)",
                        description="Evaluate every case of DIR with our renderer (fast Numba or the NumPy "
                                    "reference) in float64 or float32 and write the results to OUT in the layout "
                                    "a port writes (docs/refcheck.md §6).")
    rn.add_argument("dir")
    rn.add_argument("out")
    rn.add_argument("--renderer", choices=["fast", "reference"], default="fast")
    rn.add_argument("--dtype", choices=["float64", "float32"], default=None,
                    help="working dtype (default: the export's)")
    rn.add_argument("--cases", nargs="+", default=None, help=cases_help)
    rn.set_defaults(func=_cmd_refcheck_run)
    gs = rcs.add_parser("gsplat", help="run gsplat's PyTorch reference on the cases and compare "
                        "(docs/refcheck.md §7)",
                        description="Run gsplat 1.5.3's pure-PyTorch reference (CPU, float64; needs the optional "
                                    "torch and gsplat packages) on the render cases of DIR, then compare "
                                    "(docs/refcheck.md §7).")
    gs.add_argument("dir")
    gs.add_argument("--out", default=None, help="where gsplat's results go (default DIR/gsplat)")
    gs.add_argument("--rtol", nargs="+", default=None, help="as for compare")
    gs.add_argument("--dtype", choices=["float64", "float32"], default="float64",
                    help="gsplat's working dtype (float32: held to the float32 tolerances)")
    gs.add_argument("--cases", nargs="+", default=None, help=cases_help)
    gs.set_defaults(func=_cmd_refcheck_gsplat)
