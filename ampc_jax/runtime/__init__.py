"""Deployment: the compiled controller next to the CAN bridge (paper, "Experimental Studies").

* :mod:`~.signals` -- what the bus carries each tick (the bus vector) and the
  estimator that builds the controller's measurement from it;
* :mod:`~.step` -- :class:`RuntimeStep`, the compiled step ``f(leaves, bus)``
  and the rule of what may be sent (:func:`command_problem`);
* :mod:`~.artefact` -- the step exported with ``jax.export`` and its manifest;
* :mod:`~.runner` -- ``ampc run``'s 20 Hz loop next to ``can_bridge``;
* :mod:`~.ticklog` -- the run's logs on disk, written as the ticks run;
* :mod:`~.runcheck` -- whether a run's logs can be trusted (``ampc replay``'s checks);
* :mod:`~.plant_node` -- ``ampc plant``, the simulated vehicle on the bus
  (python-can, cantools, autosar-e2e);
* :mod:`~.replay` -- ``ampc replay``, bit for bit and what-if;
* :mod:`~.candump` -- ``ampc replay --candump``: a drive's candump log through
  the controller, compared with the commands it framed;
* :mod:`~.files` -- I/O errors that name their file;
* :mod:`~.faults` -- injected faults for the safety chain's tests.

The bus-side modules import ``can_bridge``, ``can``, ``cantools`` and ``e2e``
only inside the functions that talk to the bus (the ``runtime`` extra).
"""

from .artefact import Artefact, ArtefactError, export_step, load_artefact, read_artefact
from .faults import Fault, parse_fault
from .runcheck import CheckedRun, check_run
from .signals import BUS_FIELDS, MESSAGES, bus_from_bridge, bus_measurement, bus_vector
from .step import RuntimeStep, StepReport, command_problem
from .ticklog import RunLogError

__all__ = [
    "BUS_FIELDS",
    "MESSAGES",
    "Artefact",
    "ArtefactError",
    "CheckedRun",
    "Fault",
    "RunLogError",
    "RuntimeStep",
    "StepReport",
    "bus_from_bridge",
    "bus_measurement",
    "bus_vector",
    "check_run",
    "command_problem",
    "export_step",
    "load_artefact",
    "parse_fault",
    "read_artefact",
]
