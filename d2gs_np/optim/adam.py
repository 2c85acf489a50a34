"""Adam over named parameter blocks, with per-block learning rates and schedules.

Pure pieces in the style of optax: ``adam_init(params) -> state``,
``adam_update(grads, state, params, config) -> (params, state)``; nothing is modified in place.
``params`` and ``grads`` are ``dict[str, np.ndarray]`` (the scene layout of
``d2gs_np.scene.gaussians``, or any other named blocks such as poses or network weights).

Update of a block with gradient g, its k-th update (k = 1, 2, ...):

    m = b1 m + (1 - b1) g,  v = b2 v + (1 - b2) g^2,
    m_hat = m / (1 - b1^k),  v_hat = v / (1 - b2^k),
    p = p - lr * m_hat / (sqrt(v_hat) + eps)

which is torch.optim.Adam's (and hence 3DGS's) update up to rounding.

Choices (the paper leaves them open; docs/method.md §8):
- Step counts are per block: a block's bias correction and learning-rate schedule use the number
  of updates *that block* has received (blocks missing from ``grads`` are left alone, counters
  included). So a block that starts training late (the deformation after the warm-up) starts its
  schedule at lr_init, and 3DGS's per-iteration schedules are reproduced when every block is
  updated at every iteration. The schedule is evaluated at the step count before the update
  (0 for the first update), so the first step uses the schedule's initial value.
- A block present in ``grads`` but not in the state is given zero moments on its first update
  (e.g. a component added at a stage change).
- Moments keep the dtype of the parameters (float32 params -> float32 moments).
- Learning rates per block are looked up in ``AdamConfig.lrs`` by the exact block name
  ("dynamic.means"), then by the field name after the set prefix ("means", shared by the static
  and dynamic sets), then by the wildcard "*"; otherwise it is an error.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Mapping, Union

import numpy as np

from d2gs_np.base.checks import check_int, check_number
from d2gs_np.constants import ADAM_EPS

__all__ = [
    "Constant",
    "ExponentialDecay",
    "constant",
    "exponential_decay",
    "AdamConfig",
    "adam_init",
    "adam_update",
    "adam_update_rows",
    "adam_select",
    "adam_extend",
]


@dataclass(frozen=True)
class Constant:
    """The same learning rate at every step."""

    lr: float

    def __post_init__(self):
        check_number(self.lr, "Constant.lr", 0.0)

    def __call__(self, step: int) -> float:
        return float(self.lr)

    def to_dict(self):
        return {"kind": "constant", "lr": float(self.lr)}


@dataclass(frozen=True)
class ExponentialDecay:
    """3DGS's ``get_expon_lr_func``: log-linear from lr_init to lr_final over max_steps.

    lr(step) = delay(step) * exp((1 - s) log(lr_init) + s log(lr_final)), s = clip(step / max_steps, 0, 1),
    delay(step) = delay_mult + (1 - delay_mult) sin(pi/2 clip(step / delay_steps, 0, 1)) when
    delay_steps > 0, else 1. Held at lr_final after max_steps; 0 for step < 0 or when
    lr_init == lr_final == 0.
    """

    lr_init: float
    lr_final: float
    max_steps: int
    delay_steps: int = 0
    delay_mult: float = 1.0

    def __post_init__(self):
        check_number(self.lr_init, "ExponentialDecay.lr_init", 0.0)
        check_number(self.lr_final, "ExponentialDecay.lr_final", 0.0)
        if (self.lr_init == 0.0) != (self.lr_final == 0.0):
            raise ValueError(
                "ExponentialDecay needs lr_init and lr_final both > 0 (log-linear interpolation) or both 0; "
                f"got lr_init={self.lr_init}, lr_final={self.lr_final}"
            )
        check_int(self.max_steps, "ExponentialDecay.max_steps", 1)
        check_int(self.delay_steps, "ExponentialDecay.delay_steps", 0)
        check_number(self.delay_mult, "ExponentialDecay.delay_mult", 0.0)

    def __call__(self, step: int) -> float:
        if step < 0 or (self.lr_init == 0.0 and self.lr_final == 0.0):
            return 0.0
        if self.delay_steps > 0:
            delay = self.delay_mult + (1.0 - self.delay_mult) * math.sin(
                0.5 * math.pi * min(max(step / self.delay_steps, 0.0), 1.0)
            )
        else:
            delay = 1.0
        s = min(max(step / self.max_steps, 0.0), 1.0)
        return delay * math.exp(math.log(self.lr_init) * (1.0 - s) + math.log(self.lr_final) * s)

    def to_dict(self):
        return {
            "kind": "exponential_decay",
            "lr_init": float(self.lr_init),
            "lr_final": float(self.lr_final),
            "max_steps": int(self.max_steps),
            "delay_steps": int(self.delay_steps),
            "delay_mult": float(self.delay_mult),
        }


Schedule = Union[Constant, ExponentialDecay]


def constant(lr) -> Constant:
    """A constant learning-rate schedule."""
    return Constant(lr)


def exponential_decay(lr_init, lr_final, max_steps, delay_steps=0, delay_mult=1.0) -> ExponentialDecay:
    """3DGS's exponential learning-rate decay (``get_expon_lr_func``); see ``ExponentialDecay``."""
    return ExponentialDecay(lr_init, lr_final, max_steps, delay_steps, delay_mult)


def _schedule_from(name, spec) -> Schedule:
    if isinstance(spec, (Constant, ExponentialDecay)):
        return spec
    if isinstance(spec, Mapping):
        kind = spec.get("kind")
        args = {k: v for k, v in spec.items() if k != "kind"}
        if kind == "constant":
            return Constant(**args)
        if kind == "exponential_decay":
            return ExponentialDecay(**args)
        raise ValueError(f"learning rate of {name!r}: unknown schedule kind {kind!r}; use 'constant' or 'exponential_decay'")
    if isinstance(spec, numbers.Real) and not isinstance(spec, bool):
        return Constant(float(spec))
    raise TypeError(f"learning rate of {name!r} must be a number, a schedule or a schedule dict; got {type(spec).__name__}")


@dataclass(frozen=True)
class AdamConfig:
    """Adam hyper-parameters.

    lrs: mapping block name (or field name, or "*") -> learning rate, given as a number, a
        ``Constant`` / ``ExponentialDecay``, or their ``to_dict()`` form. Stored read-only with
        every value turned into a schedule.
    betas: (b1, b2), each in [0, 1).
    eps: added to sqrt(v_hat); default ADAM_EPS (3DGS's 1e-15).
    """

    lrs: Mapping[str, Schedule] = field(default_factory=dict)
    betas: tuple = (0.9, 0.999)
    eps: float = ADAM_EPS

    def __post_init__(self):
        if not isinstance(self.lrs, Mapping):
            raise TypeError(f"AdamConfig.lrs must be a mapping of block name -> learning rate; got {type(self.lrs).__name__}")
        lrs = {}
        for name, spec in self.lrs.items():
            if not isinstance(name, str) or not name:
                raise TypeError(f"AdamConfig.lrs keys must be non-empty strings; got {name!r}")
            lrs[name] = _schedule_from(name, spec)
        object.__setattr__(self, "lrs", MappingProxyType(lrs))
        betas = tuple(self.betas)
        if len(betas) != 2 or not all(isinstance(b, numbers.Real) and 0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"AdamConfig.betas must be two numbers in [0, 1); got {self.betas!r}")
        object.__setattr__(self, "betas", (float(betas[0]), float(betas[1])))
        check_number(self.eps, "AdamConfig.eps", 0.0, lo_open=True)

    def schedule_for(self, block: str) -> Schedule:
        """The schedule of ``block``: exact name, else field name after the set prefix, else "*"."""
        if block in self.lrs:
            return self.lrs[block]
        field_name = block.split(".", 1)[1] if "." in block else None
        if field_name is not None and field_name in self.lrs:
            return self.lrs[field_name]
        if "*" in self.lrs:
            return self.lrs["*"]
        raise ValueError(
            f"AdamConfig.lrs has no learning rate for block {block!r}; add {block!r}"
            + (f", {field_name!r}" if field_name else "") + " or '*' to lrs"
        )

    def lr(self, block: str, step: int) -> float:
        """Learning rate of ``block`` at its ``step``-th update (0-based)."""
        return float(self.schedule_for(block)(step))

    def to_dict(self):
        """JSON-ready dict; ``AdamConfig.from_dict`` inverts it."""
        return {"lrs": {k: v.to_dict() for k, v in self.lrs.items()}, "betas": list(self.betas), "eps": float(self.eps)}

    @classmethod
    def from_dict(cls, d):
        return cls(lrs=dict(d.get("lrs", {})), betas=tuple(d.get("betas", (0.9, 0.999))), eps=d.get("eps", ADAM_EPS))


# ---------------------------------------------------------------------------------------------
# State and update
# ---------------------------------------------------------------------------------------------


def _check_params(params):
    if not isinstance(params, dict):
        raise TypeError(f"params must be a dict of arrays; got {type(params).__name__}")
    for name, x in params.items():
        if not isinstance(x, np.ndarray) or x.dtype not in (np.float64, np.float32):
            got = x.dtype if isinstance(x, np.ndarray) else type(x).__name__
            raise TypeError(f"params[{name!r}] must be a float64 or float32 array; got {got}")


def adam_init(params):
    """Optimizer state for ``params``: dict(step={name: 0}, m={name: zeros}, v={name: zeros})."""
    _check_params(params)
    return {
        "step": {k: 0 for k in params},
        "m": {k: np.zeros_like(x) for k, x in params.items()},
        "v": {k: np.zeros_like(x) for k, x in params.items()},
    }


def adam_update(grads, state, params, config, lr_step_scale=1.0):
    """One Adam step on the blocks in ``grads``; returns (new params, new state).

    lr_step_scale: the learning-rate schedules are read at ``floor(count x lr_step_scale)`` where
        count is the block's own step count (the bias correction always uses the count). 1 reads
        them at the count; a time-budgeted run whose budget binds passes (schedule progress x
        total steps) / step > 1, so its decays finish when the budget does.
    grads: dict name -> gradient array (same shape and dtype as ``params[name]``); None values and
        blocks absent from ``grads`` are left alone (parameters, moments and step counts).
    state: from ``adam_init`` / a previous ``adam_update``.
    params: dict name -> array.
    config: AdamConfig.
    The inputs are not modified; untouched blocks are shared between old and new dicts.
    """
    if not isinstance(config, AdamConfig):
        raise TypeError(f"config must be an AdamConfig; got {type(config).__name__}")
    _check_params(params)
    _check_lr_step_scale(lr_step_scale)
    if not isinstance(grads, dict):
        raise TypeError(f"grads must be a dict of arrays; got {type(grads).__name__}")
    b1, b2 = config.betas
    new_params = dict(params)
    new_state = {slot: dict(blocks) for slot, blocks in state.items()}  # keeps "row_step" too
    for name, g in grads.items():
        if g is None:
            continue
        if name not in params:
            raise ValueError(f"grads has block {name!r} that params does not have")
        p = params[name]
        if not isinstance(g, np.ndarray) or g.dtype != p.dtype:
            got = g.dtype if isinstance(g, np.ndarray) else type(g).__name__
            raise TypeError(f"grads[{name!r}] must be a {p.dtype} array like params[{name!r}]; got {got}")
        if g.shape != p.shape:
            raise ValueError(f"grads[{name!r}] must have shape {p.shape} like params[{name!r}]; got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError(f"grads[{name!r}] contains NaN or inf; check the loss and its backward")
        m = state["m"].get(name)
        v = state["v"].get(name)
        if m is None or v is None:  # first update of a block added after adam_init
            m, v = np.zeros_like(p), np.zeros_like(p)
        if m.shape != p.shape:
            raise ValueError(
                f"optimizer state of {name!r} has shape {m.shape} but params has {p.shape}; after pruning or "
                "densification call adam_select / adam_extend with the same masks / counts"
            )
        step = int(state["step"].get(name, 0))
        lr = config.lr(name, _lr_step(step, lr_step_scale))
        k = step + 1
        m = b1 * m + (1.0 - b1) * g
        v = b2 * v + (1.0 - b2) * (g * g)
        m_hat = m / (1.0 - b1**k)
        v_hat = v / (1.0 - b2**k)
        new_params[name] = p - lr * m_hat / (np.sqrt(v_hat) + config.eps)
        new_state["m"][name] = m
        new_state["v"][name] = v
        new_state["step"][name] = k
    return new_params, new_state


# ---------------------------------------------------------------------------------------------
# Keeping the moments in step with pruning and densification
# ---------------------------------------------------------------------------------------------


def _prefixed(state, block_prefix):
    if not isinstance(block_prefix, str) or not block_prefix:
        raise ValueError(f"block_prefix must be a non-empty string such as 'static'; got {block_prefix!r}")
    return [k for k in state["m"] if k.startswith(block_prefix + ".")]


def _check_lr_step_scale(scale):
    check_number(scale, "lr_step_scale", 0.0, lo_open=True)


def _lr_step(count, scale):
    """The step a learning-rate schedule is read at (see ``adam_update``); exact at scale 1."""
    return count if scale == 1.0 else int(np.floor(count * scale))


def adam_update_rows(grads, rows, state, params, config, lr_step_scale=1.0, lr_factor=1.0):
    """Row-sparse Adam (as torch.optim.SparseAdam): only the rows ``rows[name]`` of each block in
    ``grads`` are updated: their moments, their parameters, and their own step counts (kept in
    ``state["row_step"][name]``, (N,) ints) for the bias correction. Rows outside the list keep
    their parameters AND moments, so per-frame blocks (camera endpoints) of frames not in the
    batch do not drift on stale momentum. Each row's learning rate is the block's schedule at
    that row's own step count (a schedule counts the visits of a row), read as in ``adam_update``
    with ``lr_step_scale``, times ``lr_factor``. Returns (new params, new state); inputs are not
    modified.
    """
    if not isinstance(config, AdamConfig):
        raise TypeError(f"config must be an AdamConfig; got {type(config).__name__}")
    _check_lr_step_scale(lr_step_scale)
    check_number(lr_factor, "lr_factor", 0.0)
    b1, b2 = config.betas
    new_params = dict(params)
    new_state = {slot: dict(blocks) for slot, blocks in state.items()}
    new_state.setdefault("row_step", {})
    for name, g in grads.items():
        if name not in params:
            raise ValueError(f"grads has block {name!r} that params does not have")
        if name not in rows:
            raise ValueError(f"adam_update_rows needs the rows of block {name!r}; pass rows={{{name!r}: indices}}")
        p = params[name]
        if not isinstance(g, np.ndarray) or g.shape != p.shape or g.dtype != p.dtype:
            raise ValueError(f"grads[{name!r}] must be a {p.dtype} array of shape {p.shape}")
        idx = np.unique(np.asarray(rows[name], dtype=np.int64))
        if idx.size and (idx[0] < 0 or idx[-1] >= p.shape[0]):
            raise ValueError(f"rows[{name!r}] must index 0..{p.shape[0] - 1}; got {idx}")
        gi = g[idx]
        if not np.all(np.isfinite(gi)):
            raise ValueError(f"grads[{name!r}] contains NaN or inf; check the loss and its backward")
        m = state["m"].get(name)
        v = state["v"].get(name)
        m = np.zeros_like(p) if m is None else m.copy()
        v = np.zeros_like(p) if v is None else v.copy()
        rs = state.get("row_step", {}).get(name)
        rs = np.zeros(p.shape[0], dtype=np.int64) if rs is None else np.array(rs, dtype=np.int64)
        step = int(state["step"].get(name, 0))
        bshape = (-1,) + (1,) * (p.ndim - 1)
        lr = np.array([lr_factor * config.lr(name, _lr_step(int(c), lr_step_scale)) for c in rs[idx]],
                      dtype=p.dtype).reshape(bshape)
        k = (rs[idx] + 1).reshape(bshape)
        m[idx] = b1 * m[idx] + (1.0 - b1) * gi
        v[idx] = b2 * v[idx] + (1.0 - b2) * (gi * gi)
        m_hat = m[idx] / (1.0 - b1**k)
        v_hat = v[idx] / (1.0 - b2**k)
        newp = p.copy()
        newp[idx] = p[idx] - lr * m_hat / (np.sqrt(v_hat) + config.eps)
        rs[idx] += 1
        new_params[name] = newp
        new_state["m"][name], new_state["v"][name] = m, v
        new_state["row_step"][name] = rs
        new_state["step"][name] = step + 1
    return new_params, new_state


def adam_select(state, block_prefix, keep_mask):
    """New state with only the rows ``keep_mask`` (bool (N,)) of every block ``f"{block_prefix}.*"``.

    Mirrors ``d2gs_np.scene.prune``: call both with the same mask. Step counts are unchanged.
    """
    keep_mask = np.asarray(keep_mask)
    if keep_mask.dtype != np.bool_ or keep_mask.ndim != 1:
        raise TypeError(f"keep_mask must be a 1-D boolean array; got dtype {keep_mask.dtype}, shape {keep_mask.shape}")
    new_state = {slot: dict(blocks) for slot, blocks in state.items()}  # keeps "row_step" too
    for name in _prefixed(state, block_prefix):
        rows = state["m"][name].shape[0]
        if rows != keep_mask.shape[0]:
            raise ValueError(f"keep_mask has {keep_mask.shape[0]} entries but optimizer state of {name!r} has {rows} rows")
        new_state["m"][name] = np.ascontiguousarray(state["m"][name][keep_mask])
        new_state["v"][name] = np.ascontiguousarray(state["v"][name][keep_mask])
    return new_state


def adam_extend(state, block_prefix, num_new):
    """New state with ``num_new`` zero-moment rows appended to every block ``f"{block_prefix}.*"``.

    Mirrors ``d2gs_np.scene.append_gaussians`` (3DGS's densification also gives new rows zero
    moments and keeps the step count). Blocks not yet in the state need nothing: they get zero
    moments at their first update.
    """
    check_int(num_new, "num_new", 0)
    new_state = {slot: dict(blocks) for slot, blocks in state.items()}  # keeps "row_step" too
    for name in _prefixed(state, block_prefix):
        for key in ("m", "v"):
            x = state[key][name]
            new_state[key][name] = np.concatenate([x, np.zeros((int(num_new),) + x.shape[1:], dtype=x.dtype)])
    return new_state
