"""Input checks shared by the scene loader and the configs: the warning categories and the checks
of one value (a real number, an integer, a flag, one of a few choices) that every config uses.

Impossible input is refused with a ValueError (the CLI prints it as one line and exits with
status 2). Input that is possible but implausible is accepted with a warning: a Python warning of
category ``InputWarning`` (``SceneWarning`` for a scene folder, ``ConfigWarning`` for a config),
one line naming the values, the plausible range and why. The CLI prints each as
``d2gs CMD: warning: ...`` and a training run also records it in its log; elsewhere Python's
warning machinery shows it (or a caller filters it, ``warnings.simplefilter``).
"""
from __future__ import annotations

import math
import numbers
import warnings

import numpy as np

__all__ = ["InputWarning", "SceneWarning", "ConfigWarning", "warn", "check_number", "check_scalar", "check_int",
           "check_bool",
           "check_choice", "name_items"]


class InputWarning(UserWarning):
    """Input accepted, but implausible: the message says which values, the range and why."""


class SceneWarning(InputWarning):
    """A scene folder's content (docs/dataset_format.md) accepted with a warning."""


class ConfigWarning(InputWarning):
    """An experiment config's value accepted with a warning."""


def warn(message: str, category=SceneWarning, stacklevel: int = 2):
    """Issue one warning line of ``category`` (an ``InputWarning``) from the caller."""
    warnings.warn(message, category, stacklevel=stacklevel + 1)


def _bounds(lo, hi, lo_open, hi_open, fmt=format) -> str:
    """How the allowed range reads after 'must be a number': '', ' >= 0', ' < 1' or ' in (0, 1]'."""
    low, high = lo is not None and lo > -math.inf, hi is not None and hi < math.inf
    if low and high:
        return f" in {'(' if lo_open else '['}{fmt(lo)}, {fmt(hi)}{')' if hi_open else ']'}"
    if low:
        return f" {'>' if lo_open else '>='} {fmt(lo)}"
    if high:
        return f" {'<' if hi_open else '<='} {fmt(hi)}"
    return ""


def _refuse(name, what, bounds, hint, value):
    raise ValueError(f"{name} must be {what}{bounds}" + (f" ({hint})" if hint else "") + f"; got {value!r}")


def _inside(v, lo, hi, lo_open, hi_open) -> bool:
    return ((lo is None or (lo < v if lo_open else lo <= v))
            and (hi is None or (v < hi if hi_open else v <= hi)))


def check_number(value, name, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False, hint=""):
    """``float(value)`` if it is a finite real number (not a bool; NumPy scalars too) in the interval
    from ``lo`` to ``hi`` (closed unless ``lo_open`` / ``hi_open``); else ValueError naming ``name``,
    the range, ``hint`` (what the value means, or the fix) and the value, e.g.
    ``LossConfig.lambda_gs must be a finite number >= 0 (0 = term off); got -1``."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    try:
        v = float(value) if ok else math.nan
    except OverflowError:  # an int too large for a float
        v = math.nan
    if not (math.isfinite(v) and _inside(v, lo, hi, lo_open, hi_open)):
        _refuse(name, "a finite number", _bounds(lo, hi, lo_open, hi_open, lambda b: f"{b:g}"), hint, value)
    return v


def check_scalar(value, name, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False, hint=""):
    """``check_number`` of a function argument that may also come as a 0-d NumPy array; an array of
    any other shape is refused as not a scalar."""
    if isinstance(value, np.ndarray):
        if value.shape != ():
            raise ValueError(f"{name} must be a scalar; got an array of shape {value.shape}")
        value = value[()]
    return check_number(value, name, lo, hi, lo_open, hi_open, hint)


def check_int(value, name, lo=None, hi=None, hint=""):
    """``int(value)`` if it is an integer (not a bool, not a float such as 2.0; NumPy integers too)
    with ``lo <= value <= hi`` (either bound None: none); else ValueError, e.g.
    ``TrainConfig.iters must be an integer >= 1; got 0``."""
    if not (isinstance(value, numbers.Integral) and not isinstance(value, bool)
            and _inside(int(value), lo, hi, False, False)):
        _refuse(name, "an integer", _bounds(lo, hi, False, False, str), hint, value)
    return int(value)


def check_bool(value, name, hint=""):
    """``bool(value)`` if it is True or False (a NumPy bool too; not 0 / 1 or a string); else
    ValueError, e.g. ``DensifyConfig.absgrad must be true or false; got 'yes'``."""
    if not isinstance(value, (bool, np.bool_)):
        _refuse(name, "true or false", "", hint, value)
    return bool(value)


def check_choice(value, name, choices, hint=""):
    """``value`` if it is one of ``choices`` (a tuple of strings); else ValueError, e.g.
    ``TrainConfig.blur must be one of ('auto', 'on', 'off'); got 'maybe'``."""
    if not (isinstance(value, str) and value in choices):
        _refuse(name, f"one of {tuple(choices)}", "", hint, value)
    return value


def name_items(labels, limit: int = 4) -> str:
    """'a, b and c', at most ``limit`` named, then 'and N more'."""
    labels = list(labels)
    if len(labels) <= limit:
        return labels[0] if len(labels) == 1 else ", ".join(labels[:-1]) + " and " + labels[-1]
    return ", ".join(labels[:limit]) + f" and {len(labels) - limit} more"
