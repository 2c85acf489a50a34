"""Optimizers: Adam over named parameter blocks (``adam``)."""
from d2gs_np.optim.adam import (
    AdamConfig,
    Constant,
    ExponentialDecay,
    adam_extend,
    adam_init,
    adam_select,
    adam_update,
    adam_update_rows,
    constant,
    exponential_decay,
)

__all__ = [
    "AdamConfig", "Constant", "ExponentialDecay", "constant", "exponential_decay",
    "adam_init", "adam_update", "adam_update_rows", "adam_select", "adam_extend",
]
