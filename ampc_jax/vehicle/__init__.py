"""The paper's vehicle examples on a nonlinear plant (section "Examples on Vehicle Control").

* :mod:`~.params` -- vehicle data, wheel geometry, the :class:`Measurement`;
* :mod:`~.models` -- what the control models share, and the settings base;
* :mod:`~.cruise`, :mod:`~.stability` -- the two examples (:data:`CRUISE`,
  :data:`STABILITY`), registered in :data:`EXAMPLES` (:mod:`~.examples`);
* :mod:`~.plant` -- the nonlinear double-track plant;
* :mod:`~.manoeuvres` -- paths, drivers and the test manoeuvres (:data:`SCENARIOS`).
"""

from .cruise import CRUISE, CruiseSettings
from .examples import EXAMPLES, VehicleExample, example, register_example
from .manoeuvres import SCENARIOS, DriverParams, Scenario, ScenarioSpec, register_scenario
from .models import ControlModel, ExampleSettings
from .params import CONTROL_DT, WHEELS, Measurement, VehicleParams
from .stability import STABILITY, StabilitySettings

__all__ = [
    "CONTROL_DT",
    "CRUISE",
    "EXAMPLES",
    "SCENARIOS",
    "STABILITY",
    "WHEELS",
    "ControlModel",
    "CruiseSettings",
    "DriverParams",
    "ExampleSettings",
    "Measurement",
    "Scenario",
    "ScenarioSpec",
    "StabilitySettings",
    "VehicleExample",
    "VehicleParams",
    "example",
    "register_example",
    "register_scenario",
]
