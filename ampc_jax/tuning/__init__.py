"""Gradient tuning: the solver's speed (:mod:`.solver`), the objectives' weights
through the differentiable closed loop (:mod:`.weights`) and a learned start
(:mod:`.warm_start`), each through one training loop (:mod:`.fit`). What they
write, the tuned-parameters file, is configuration I/O
(:mod:`ampc_jax.io.params_file`); its names are re-exported here."""

from __future__ import annotations

from ..io.params_file import (
    PARAMS_FORMAT,
    TunedParams,
    apply_params,
    read_params,
    validate_params,
    write_params,
)
from .weights import (
    LossOptions,
    LossTerms,
    WeightsResult,
    evaluate_settings,
    log_weights,
    loop_loss,
    soft_max,
    tune_weights,
    weight_fields,
    with_log_weights,
)

__all__ = [
    "LossOptions",
    "LossTerms",
    "PARAMS_FORMAT",
    "WeightsResult",
    "evaluate_settings",
    "log_weights",
    "loop_loss",
    "soft_max",
    "tune_weights",
    "weight_fields",
    "with_log_weights",
    "TunedParams",
    "apply_params",
    "read_params",
    "validate_params",
    "write_params",
]
