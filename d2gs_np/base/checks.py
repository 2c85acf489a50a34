"""Input checks shared by the scene loader and the configs: the warning categories and a range check.

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

__all__ = ["InputWarning", "SceneWarning", "ConfigWarning", "warn", "check_number", "name_items"]


class InputWarning(UserWarning):
    """Input accepted, but implausible: the message says which values, the range and why."""


class SceneWarning(InputWarning):
    """A scene folder's content (docs/dataset_format.md) accepted with a warning."""


class ConfigWarning(InputWarning):
    """An experiment config's value accepted with a warning."""


def warn(message: str, category=SceneWarning, stacklevel: int = 2):
    """Issue one warning line of ``category`` (an ``InputWarning``) from the caller."""
    warnings.warn(message, category, stacklevel=stacklevel + 1)


def _interval(lo, hi, lo_open, hi_open):
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def check_number(value, name, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False, hint=""):
    """``float(value)`` if it is a finite real number (not a bool) in the interval from ``lo`` to
    ``hi`` (closed unless ``lo_open`` / ``hi_open``); else ValueError naming ``name``, the interval,
    the value and ``hint`` (what the value means, or the fix)."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)  # NumPy scalars too
    try:
        v = float(value) if ok else math.nan
    except OverflowError:  # an int too large for a float
        v = math.nan
    ok = math.isfinite(v) and (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
    if not ok:
        raise ValueError(f"{name} must be a finite number in {_interval(lo, hi, lo_open, hi_open)}"
                         + (f" ({hint})" if hint else "") + f"; got {value!r}")
    return v


def name_items(labels, limit: int = 4) -> str:
    """'a, b and c', at most ``limit`` named, then 'and N more'."""
    labels = list(labels)
    if len(labels) <= limit:
        return labels[0] if len(labels) == 1 else ", ".join(labels[:-1]) + " and " + labels[-1]
    return ", ".join(labels[:limit]) + f" and {len(labels) - limit} more"
