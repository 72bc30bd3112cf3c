"""Files in and out: the tuned-parameters file (:mod:`~.params_file`, read by
``ampc simulate``, ``solve``, ``run`` and ``export``, written by ``ampc tune``),
and the outputs of closed-loop runs: CSV and JSON (:mod:`~.reports`), figures
(:mod:`~.figures`)."""

from .params_file import (
    PARAMS_FORMAT,
    TunedParams,
    apply_params,
    read_params,
    tuned_for_differences,
    tuned_for_warning,
    validate_params,
    write_params,
)

__all__ = [
    "PARAMS_FORMAT",
    "TunedParams",
    "apply_params",
    "read_params",
    "tuned_for_differences",
    "tuned_for_warning",
    "validate_params",
    "write_params",
]
