"""Gradient tuning: the solver's speed (:mod:`.solver`) and the tuned-parameters file
(:mod:`.params_file`)."""

from __future__ import annotations

from .params_file import (
    PARAMS_FORMAT,
    TunedParams,
    apply_params,
    read_params,
    validate_params,
    write_params,
)

__all__ = [
    "PARAMS_FORMAT",
    "TunedParams",
    "apply_params",
    "read_params",
    "validate_params",
    "write_params",
]
