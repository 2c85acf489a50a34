"""Files of the reference-check kit: one ``NAME.npz`` per case plus ``cases.json`` (docs/refcheck.md §3).

A case file holds flat keys ``in.<name>`` (inputs), ``cot.<name>`` (the fixed upstream gradient
of output <name>), ``out.<name>`` (outputs) and ``grad.<name>`` (gradients of
L = sum over outputs of <cot.name, out.name> with respect to input <name>). Another
implementation's results use the same layout; only ``out.*`` and ``grad.*`` are read from them.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

__all__ = ["FORMAT", "VERSION", "SECTIONS", "write_case", "read_case", "write_index", "read_index",
           "write_results", "case_path"]

FORMAT = "d2gs_np-refcheck"
VERSION = 1
SECTIONS = ("in", "cot", "out", "grad")
INDEX = "cases.json"
DOCUMENTATION = "docs/refcheck.md §3"


def case_path(directory, name):
    return Path(directory) / f"{name}.npz"


def _flat(sections):
    flat = {}
    for sec, arrays in sections.items():
        if sec not in SECTIONS:
            raise ValueError(f"unknown section {sec!r}; expected one of {SECTIONS}")
        for key, val in arrays.items():
            flat[f"{sec}.{key}"] = np.asarray(val)
    return flat


def _atomic_savez(path, flat):
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **flat)
    os.replace(tmp, path)


def write_case(directory, name, inputs, cotangents, outputs, gradients):
    """Write ``directory/name.npz`` with the four sections; returns its path."""
    path = case_path(directory, name)
    _atomic_savez(path, _flat({"in": inputs, "cot": cotangents, "out": outputs, "grad": gradients}))
    return path


def write_results(directory, name, outputs, gradients):
    """Write another implementation's (or a rerun's) results: only ``out.*`` and ``grad.*``."""
    Path(directory).mkdir(parents=True, exist_ok=True)
    path = case_path(directory, name)
    _atomic_savez(path, _flat({"out": outputs, "grad": gradients}))
    return path


def read_case(path):
    """{section: {name: array}} of a case file (sections absent from the file are empty dicts)."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"refcheck case file {path} is a folder; each case is one NAME.npz file")
    if not path.is_file():
        raise FileNotFoundError(f"refcheck case file {path} does not exist")
    out = {sec: {} for sec in SECTIONS}
    try:
        z = np.load(path, allow_pickle=False)
    except Exception:  # BadZipFile, EOFError, pickled data ...: NumPy's text would advise allow_pickle
        raise ValueError(f"refcheck case file {path} is not a readable .npz (truncated, corrupt or another "
                         "format); write it again with np.savez of plain numeric arrays") from None
    with z:
        for key in z.files:
            sec, _, name = key.partition(".")
            if sec not in out or not name:
                raise ValueError(f"{path}: key {key!r} is not <section>.<name> with section in {SECTIONS}")
            try:
                out[sec][name] = z[key]
            except ValueError:  # an object array (needs pickle) cannot be read safely
                raise ValueError(f"{path}: array {key!r} holds Python objects (an object array); write plain "
                                 "numeric arrays (float or int) with np.savez") from None
            except Exception:  # a member cut short or damaged inside the zip
                raise ValueError(f"{path}: array {key!r} is unreadable (truncated or corrupt file); write the file "
                                 "again") from None
    return out


def _describe(arrays):
    return {k: {"shape": list(np.shape(v)), "dtype": str(np.asarray(v).dtype)} for k, v in arrays.items()}


def _json_number(x):
    x = float(x)
    return None if not math.isfinite(x) else x  # inf margin (nothing to be near) -> null


def case_entry(case, outputs, gradients, inputs, cotangents):
    """The cases.json entry of one case."""
    return {
        "name": case.name, "file": f"{case.name}.npz", "kind": case.kind, "description": case.description,
        "condition": float(case.condition),
        "margins": {view: {k: _json_number(v) for k, v in m.items()} for view, m in case.margins.items()},
        "inputs": _describe(inputs), "cotangents": _describe(cotangents),
        "outputs": _describe(outputs), "gradients": _describe(gradients),
    }


def write_index(directory, dtype, entries):
    """Write ``directory/cases.json``."""
    index = {"format": FORMAT, "version": VERSION, "dtype": str(np.dtype(dtype)),
             "golden_dtype": "float64", "documentation": DOCUMENTATION, "cases": entries}
    path = Path(directory) / INDEX
    tmp = path.with_name(INDEX + ".tmp")
    tmp.write_text(json.dumps(index, indent=1))
    os.replace(tmp, path)
    return path


def read_index(directory):
    """The parsed ``cases.json`` of an export folder (clear errors for a missing or foreign one)."""
    path = Path(directory) / INDEX
    if Path(directory).exists() and not Path(directory).is_dir():
        raise ValueError(f"refcheck folder {directory} is a file, not a folder; pass the folder made by "
                         "'d2gs refcheck export DIR'")
    if not Path(directory).is_dir():
        raise FileNotFoundError(f"refcheck folder {directory} does not exist; create it with "
                                f"'d2gs refcheck export {directory}'")
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: {directory} is not a refcheck export "
                                f"(make one with 'd2gs refcheck export DIR')")
    try:
        index = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}); export the folder again "
                         f"('d2gs refcheck export {directory}')") from None
    if not isinstance(index, dict):
        raise ValueError(f"{path} holds a JSON {type(index).__name__}, not a refcheck index (an object); export "
                         f"the folder again ('d2gs refcheck export {directory}')")
    if index.get("format") != FORMAT:
        raise ValueError(f"{path} has format {index.get('format')!r}, expected {FORMAT!r}")
    if index.get("version") != VERSION:
        raise ValueError(f"{path} has version {index.get('version')!r}; this code reads version {VERSION}")
    if not isinstance(index.get("cases"), list) or not all(isinstance(e, dict) and isinstance(e.get("name"), str)
                                                           for e in index["cases"]):
        raise ValueError(f"{path}: 'cases' must be a list of objects with a 'name'; export the folder again "
                         f"('d2gs refcheck export {directory}')")
    return index
