"""``d2gs refcheck compare``: another implementation's results against our golden ones (docs/refcheck.md §5).

For every case of the export and every quantity (each ``out.*`` and ``grad.*`` of our file):

    err = |theirs - ours| entrywise,  scale = max |ours| over the quantity (1 if that is 0),
    max_abs = max err,  max_rel = max_abs / scale,  where = index of max err (named axes),
    pass  <=>  finite, same shape, and max_abs <= rtol * condition * scale

with rtol per quantity and dtype (``default_rtol``; the case's ``condition`` from cases.json
widens it for ill-conditioned cases); integer radii compare exactly in float64 and within one
pixel in float32. A case file or quantity that theirs lacks fails as MISSING.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d2gs_np import constants as C
from d2gs_np.refcheck.io import case_path, read_case, read_index

__all__ = ["Row", "compare_dirs", "default_rtol", "format_table", "parse_rtol"]

# Axis names of every quantity, for the "where" column (docs/refcheck.md §3).
_IMG = ("cam", "row", "col", "ch")
_GAUSS = ("gaussian", "comp")
AXES = {
    "out.image": _IMG, "out.alpha": _IMG, "out.depth": _IMG, "out.expected_depth": _IMG,
    "out.radii": ("cam", "gaussian", "axis"), "out.means2d": ("cam", "gaussian", "uv"),
    "out.depths": ("cam", "gaussian"), "out.conics": ("cam", "gaussian", "abc"),
    "out.viewmats_virtual": ("view", "row", "col"),
    "out.means": _GAUSS, "out.quats": _GAUSS, "out.colors": _GAUSS,
    "grad.means": _GAUSS, "grad.quats": _GAUSS, "grad.scales": _GAUSS, "grad.opacities": ("gaussian",),
    "grad.colors": _GAUSS, "grad.viewmats": ("cam", "row", "col"), "grad.viewmats_tangent": ("cam", "comp"),
    "grad.backgrounds": ("cam", "ch"), "grad.means2d": ("cam", "gaussian", "uv"),
    "grad.xi_start": ("comp",), "grad.xi_end": ("comp",), "grad.virtual_tangents": ("view", "comp"),
    "grad.base_means": _GAUSS, "grad.base_quats": _GAUSS, "grad.base_colors": _GAUSS,
    "grad.coef_means": ("gaussian", "coef", "comp"), "grad.coef_quats": ("gaussian", "coef", "comp"),
    "grad.coef_colors": ("gaussian", "coef", "comp"),
}


def default_rtol(quantity, dtype):
    """The documented default relative tolerance of a quantity ("out.x" or "grad.x") for an
    export of ``dtype`` (constants REFCHECK_*; their reasons are given there)."""
    if np.dtype(dtype) == np.float64:
        return C.REFCHECK_RTOL_F64
    return C.REFCHECK_RTOL_F32_GRAD if quantity.startswith("grad.") else C.REFCHECK_RTOL_F32_OUTPUT


def parse_rtol(values):
    """--rtol values -> (global override or None, {quantity: rtol}).

    Each value is a number (every float quantity) or QUANTITY=NUMBER, e.g. grad.viewmats=1e-8.
    """
    glob, per = None, {}
    for v in values or ():
        name, eq, num = str(v).rpartition("=")
        try:
            x = float(num)
        except ValueError:
            raise ValueError(f"--rtol takes NUMBER or QUANTITY=NUMBER (e.g. grad.means=1e-8); got {v!r}") from None
        if not (x >= 0 and np.isfinite(x)):
            raise ValueError(f"--rtol must be a finite number >= 0; got {v!r}")
        if eq:
            if not name.startswith(("out.", "grad.")):
                raise ValueError(f"--rtol quantity must be out.<name> or grad.<name>; got {name!r}")
            per[name] = x
        else:
            glob = x
    return glob, per


@dataclass
class Row:
    """One line of the comparison table."""

    case: str
    quantity: str
    status: str  # "pass", "FAIL", "MISSING"
    max_abs: float = float("nan")
    max_rel: float = float("nan")
    where: str = ""
    tol: float = float("nan")
    note: str = ""

    @property
    def ok(self):
        return self.status == "pass"


def _where(quantity, idx):
    axes = AXES.get(quantity, ())
    names = [axes[i] if i < len(axes) else f"i{i}" for i in range(len(idx))]
    return ", ".join(f"{a}={int(i)}" for a, i in zip(names, idx)) if idx else "(scalar)"


def compare_quantity(case, quantity, ours, theirs, rtol, integer_atol=0):
    """One Row: ``theirs`` against ``ours`` for a quantity (rtol already scaled by the condition)."""
    ours = np.asarray(ours)
    if theirs is None:
        return Row(case, quantity, "MISSING", tol=rtol, note="not in their file")
    theirs = np.asarray(theirs)
    if theirs.shape != ours.shape:
        return Row(case, quantity, "FAIL", tol=rtol, note=f"shape {theirs.shape}, expected {ours.shape}")
    if theirs.dtype.kind not in "fiub":
        return Row(case, quantity, "FAIL", tol=rtol, note=f"dtype {theirs.dtype} is not numeric")
    t64 = theirs.astype(np.float64)
    o64 = ours.astype(np.float64)
    bad = ~np.isfinite(t64)
    if np.any(bad):
        idx = tuple(np.argwhere(bad)[0])
        return Row(case, quantity, "FAIL", where=_where(quantity, idx), tol=rtol,
                   note=f"{np.count_nonzero(bad)} non-finite value(s), first {t64[idx]}")
    if ours.size == 0:
        return Row(case, quantity, "pass", 0.0, 0.0, "(empty)", rtol)
    err = np.abs(t64 - o64)
    flat = int(np.argmax(err))
    idx = np.unravel_index(flat, err.shape)
    max_abs = float(err[idx])
    where = _where(quantity, idx) + f" (ours {o64[idx]:.17g}, theirs {t64[idx]:.17g})"
    if ours.dtype.kind in "iub":  # radii: integers, absolute
        ok = max_abs <= integer_atol
        return Row(case, quantity, "pass" if ok else "FAIL", max_abs, max_abs, where, float(integer_atol),
                   "" if ok else f"integers differ by more than {integer_atol}")
    peak = float(np.abs(o64).max())
    scale = peak if peak > 0 else 1.0
    max_rel = max_abs / scale
    ok = max_abs <= rtol * scale
    return Row(case, quantity, "pass" if ok else "FAIL", max_abs, max_rel, where, rtol,
               "" if ok or peak > 0 else "ours is all zero: theirs must be within rtol absolutely")


def compare_dirs(ours_dir, theirs_dir, rtol=None, cases=None, tolerances=None):
    """Compare every (selected) case; returns (rows, ok).

    rtol: None (documented defaults), a float (every float quantity), or a (global, {quantity:
    rtol}) pair from ``parse_rtol``. cases: names to compare (default all of the export).
    tolerances: "float64" or "float32", the set of default tolerances (default: the export's
    dtype; "float32" for a float32 implementation run on a float64 export).
    """
    index = read_index(ours_dir)
    if Path(theirs_dir).exists() and not Path(theirs_dir).is_dir():
        raise ValueError(f"results folder {theirs_dir} is a file; pass the folder of NAME.npz results")
    if not Path(theirs_dir).is_dir():
        raise FileNotFoundError(f"results folder {theirs_dir} does not exist")
    if tolerances not in (None, "float64", "float32"):
        raise ValueError(f"tolerances must be 'float64' or 'float32'; got {tolerances!r}")
    dtype = np.dtype(index["dtype"] if tolerances is None else tolerances)
    glob, per = (rtol if isinstance(rtol, tuple) else (rtol, {}))
    names = [e["name"] for e in index["cases"]]
    for name in cases or ():
        if name not in names:
            raise ValueError(f"case {name!r} is not in {ours_dir}; it has: {', '.join(names)}")
    rows = []
    for entry in index["cases"]:
        name = entry["name"]
        if cases and name not in cases:
            continue
        ours = read_case(case_path(ours_dir, name))
        tpath = case_path(theirs_dir, name)
        if not tpath.is_file():
            rows.append(Row(name, "*", "MISSING", note=f"no file {tpath}"))
            continue
        theirs = read_case(tpath)
        cond = float(entry.get("condition", 1.0))
        radii_atol = 0 if dtype == np.float64 else C.REFCHECK_RADII_ATOL_F32
        for sec in ("out", "grad"):
            for key, val in ours[sec].items():
                q = f"{sec}.{key}"
                tol = per.get(q, glob if glob is not None else default_rtol(q, dtype)) * cond
                rows.append(compare_quantity(name, q, val, theirs[sec].get(key), tol, radii_atol))
    return rows, all(r.ok for r in rows)


def format_table(rows):
    """The comparison table as text: one line per (case, quantity), then a summary."""
    head = f"{'case':<20s} {'quantity':<22s} {'max abs':>10s} {'max rel':>10s} {'rtol':>8s} {'result':<7s} worst at"
    lines = [head, "-" * len(head)]
    for r in rows:
        f = lambda x: "-" if not np.isfinite(x) else f"{x:10.3g}"  # noqa: E731
        where = r.where + (f"  [{r.note}]" if r.note else "")
        lines.append(f"{r.case:<20s} {r.quantity:<22s} {f(r.max_abs):>10s} {f(r.max_rel):>10s} "
                     f"{('-' if not np.isfinite(r.tol) else f'{r.tol:.1g}'):>8s} {r.status:<7s} {where}")
    failed = [r for r in rows if not r.ok]
    ncases = len({r.case for r in rows})
    lines.append(f"{len(rows)} quantities in {ncases} cases: {len(rows) - len(failed)} passed, {len(failed)} failed")
    for r in failed:
        lines.append(f"FAILED {r.case} {r.quantity}: {r.status} {r.where} {r.note}".rstrip())
    return "\n".join(lines)
