"""``d2gs refcheck export`` and ``d2gs refcheck run`` (docs/refcheck.md §1-3).

export: build the named cases, store their inputs and upstream gradients in the chosen dtype,
and our float64 outputs and gradients computed from exactly those stored inputs.
run: evaluate every case of an export with our own code (either renderer, either dtype) and
write the results in the layout another implementation uses, so compare can be tried on it.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from d2gs_np.refcheck.cases import DEFAULT_CASES, DEFAULT_CASES_F32, build_case
from d2gs_np.refcheck.compute import compute, resolve_renderer
from d2gs_np.refcheck.io import case_entry, case_path, read_case, read_index, write_case, write_index, write_results

__all__ = ["export", "run"]


def _check_dtype(dtype):
    try:
        dt = np.dtype(dtype)
    except TypeError:
        dt = None
    if dt not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise ValueError(f"dtype must be 'float64' or 'float32'; got {dtype!r}")
    return dt


def _cast(arrays, dtype):
    """Float arrays cast to dtype; integer and boolean scalars kept."""
    return {k: (np.asarray(v, dtype=dtype) if np.asarray(v).dtype.kind == "f" else np.asarray(v))
            for k, v in arrays.items()}


def export(directory, cases=None, dtype="float64", log=print):
    """Write the cases (default: ``DEFAULT_CASES``, or ``DEFAULT_CASES_F32`` for float32) and
    ``cases.json`` into ``directory``.

    Inputs and upstream gradients are stored in ``dtype``; our outputs and gradients are always
    computed in float64 from those stored values (for float32, from the float32 inputs widened
    exactly), so they are the golden answer for exactly the inputs in the file.
    Returns the list of cases.json entries.
    """
    dtype = _check_dtype(dtype)
    default = DEFAULT_CASES if dtype == np.float64 else DEFAULT_CASES_F32
    names = list(default if not cases else cases)
    for name in names:  # every name is checked before any work
        if name not in DEFAULT_CASES:
            raise ValueError(f"unknown refcheck case {name!r}; known cases: {', '.join(DEFAULT_CASES)}")
    if len(set(names)) != len(names):
        raise ValueError(f"--cases lists a case twice: {names}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    entries = []
    for name in names:
        t0 = time.perf_counter()
        case = build_case(name)
        inputs, cot = _cast(case.inputs, dtype), _cast(case.cotangents, dtype)
        outputs, grads = compute(case.kind, _cast(inputs, np.float64), _cast(cot, np.float64), np.float64, "fast")
        for sec, arrays in (("out", outputs), ("grad", grads)):
            for key, val in arrays.items():
                if not np.all(np.isfinite(val)):
                    raise RuntimeError(f"case {name}: our {sec}.{key} is not finite (a bug in the case or the code)")
        write_case(directory, name, inputs, cot, outputs, grads)
        entries.append(case_entry(case, outputs, grads, inputs, cot))
        if log:
            log(f"[refcheck] {name:<20s} {case.kind:<6s} {time.perf_counter() - t0:6.2f}s  {case.description}")
    write_index(directory, dtype, entries)
    return entries


def run(export_dir, out_dir, renderer="fast", dtype=None, cases=None, log=print):
    """Evaluate the export's cases with our own code and write ``out.*``/``grad.*`` files to out_dir.

    renderer: "fast" or "reference".  dtype: working dtype (default: the export's input dtype).
    """
    index = read_index(export_dir)
    dtype = _check_dtype(index["dtype"] if dtype is None else dtype)
    resolve_renderer(renderer)
    names = [e["name"] for e in index["cases"]]
    for name in cases or ():
        if name not in names:
            raise ValueError(f"case {name!r} is not in {export_dir}; it has: {', '.join(names)}")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    for entry in index["cases"]:
        if cases and entry["name"] not in cases:
            continue
        t0 = time.perf_counter()
        data = read_case(case_path(export_dir, entry["name"]))
        outputs, grads = compute(entry["kind"], data["in"], data["cot"], dtype, renderer)
        write_results(out_dir, entry["name"], outputs, grads)
        if log:
            log(f"[refcheck] ran {entry['name']:<20s} ({renderer}, {dtype}) in {time.perf_counter() - t0:.2f}s")
