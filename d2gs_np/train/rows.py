"""One place where the number of Gaussians changes: ``resize_rows``.

Three things are indexed by Gaussian, row for row, and must change together whenever a set gains
or loses rows (pruning, densification, and any later initialisation or densification rule):

- the parameter blocks of the set (``scene/gaussians.py``: ``static.*``, ``dynamic.*``);
- the Adam moments of those blocks (``optim/adam.py``; step counts are per block and stay);
- per-row statistics kept between steps, ``rows``: a dict name -> {set: (N_set,) array}, e.g. the
  accumulated screen-space gradients of densification (``train/densify.py``). Appended rows
  start at zero. Their checkpoint keys are ``f"{name}/{set}"``.

A rule that changes the rows computes *which* rows (a keep mask, new rows) and lets
``resize_rows`` apply it, so no rule can forget one of the three. Anything else indexed by rows
(e.g. nearest-neighbour lists of a smoothness regulariser) must be rebuilt after a resize; a plugin
can detect one by the row counts changing.
"""
from __future__ import annotations

import numpy as np

from d2gs_np.optim import adam
from d2gs_np.scene import gaussians
from d2gs_np.scene.gaussians import DYNAMIC, STATIC

__all__ = ["SETS", "resize_rows", "num_rows"]

SETS = (STATIC, DYNAMIC)


def num_rows(params, prefix) -> int:
    """Rows of one set (0 for a set the scene does not have)."""
    name = f"{prefix}.means"
    return params[name].shape[0] if name in params else 0


def resize_rows(params, adam_state, rows, prefix, keep=None, new=None):
    """Append rows to one set, then keep a subset; parameters, Adam state and statistics alike.

    params: parameter dict; adam_state: its Adam state; rows: per-row statistics (module
    docstring). prefix: "static" or "dynamic".
    new: None, or a dict holding every block ``f"{prefix}.{field}"`` of the set, (M, ...) rows
        to append (zero Adam moments, zero statistics).
    keep: None, or (N + M,) bool over the rows after appending; rows flagged False are removed.
    Returns (params, adam_state, rows), new dicts; the inputs are not modified.
    """
    if prefix not in SETS:
        raise ValueError(f"prefix must be one of {SETS}; got {prefix!r}")
    if new is not None:
        m = int(new[f"{prefix}.means"].shape[0])
        params = gaussians.append_gaussians(params, new)
        adam_state = adam.adam_extend(adam_state, prefix, m)
        rows = {name: {**per, prefix: np.concatenate([per[prefix], np.zeros(m, per[prefix].dtype)])}
                for name, per in rows.items()}
    if keep is not None:
        keep = np.asarray(keep)
        params = gaussians.select_rows(params, prefix, keep)
        adam_state = adam.adam_select(adam_state, prefix, keep)
        rows = {name: {**per, prefix: per[prefix][keep]} for name, per in rows.items()}
    return params, adam_state, rows
