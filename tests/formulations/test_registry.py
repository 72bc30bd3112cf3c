"""The registry of formulations (ampc_jax.formulations.registry): a new formulation is
one class that declares what it is plus one ``register_formulation`` line, and then
runs through ``ampc solve``, ``ampc sweep`` and ``ampc simulate`` with nothing else
changed; every list of formulations in the package is read from the registry."""

import functools
import json
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np
import pyarrow.parquet as pq
import pytest

from ampc_jax.admm import ADMMSolver, FormulationInfo
from ampc_jax.cli import main
from ampc_jax.closed_loop import SimConfig, loop_formulations
from ampc_jax.formulations import (
    FORMULATIONS,
    LocalExplicit,
    check_formulation,
    formulation,
    formulation_info,
    formulation_names,
    register_formulation,
    unregister_formulation,
)
from ampc_jax.generate import random_problem
from ampc_jax.problem import Topology
from ampc_jax.sweep.run import SweepSpec

pytestmark = pytest.mark.timeout(300)


@dataclass(frozen=True)
class ToyExplicit(ADMMSolver):
    """A fifth formulation for the test: Local Explicit with the dense KKT solve,
    reached through the core protocol only (what a new formulation file holds)."""

    info = FormulationInfo(
        name="toy_explicit",
        title="a toy formulation (Local Explicit, dense KKT)",
        label="Toy",
        rho="objective",
        rho_basis="opt_ro",
        decomposed=True,
        batch_kkt="dense",
        closed_loop=True,
    )

    topology: Topology
    max_iter: int = 500
    anderson: int = 0
    kkt: str = "dense"
    rho_method: str = "power"

    @functools.cached_property
    def explicit(self) -> LocalExplicit:
        return LocalExplicit(
            self.topology,
            max_iter=self.max_iter,
            anderson=self.anderson,
            kkt=self.kkt,
            rho_method=self.rho_method,
            finish="none",  # the iteration alone (a finish is a formulation's own option)
        )

    @property
    def n_rho(self) -> int:
        return self.explicit.n_rho

    def setup(self, data: Any, params: Any = None) -> Any:
        return self.explicit.setup(data, params)

    def init(self, setup: Any, warm: Any = None) -> Any:
        return self.explicit.init(setup, warm)

    def step(self, setup: Any, state: Any) -> Any:
        return self.explicit.step(setup, state)

    def converged(self, setup: Any, state: Any) -> Any:
        return self.explicit.converged(setup, state)

    def result(self, setup: Any, state: Any) -> Any:
        return self.explicit.result(setup, state)

    def point(self, state: Any) -> Any:
        return self.explicit.point(state)

    def at(self, x: Any, state: Any) -> Any:
        return self.explicit.at(x, state)

    def cold_state(self, dtype: Any = None) -> Any:
        return self.explicit.cold_state(dtype)

    def shift(self, state: Any, steps: int = 1) -> Any:
        return self.explicit.shift(state, steps)


@pytest.fixture
def toy():
    register_formulation(ToyExplicit)  # the one registry line
    yield "toy_explicit"
    unregister_formulation("toy_explicit")


def test_the_registry_describes_the_four_formulations():
    assert tuple(FORMULATIONS) == (
        "local_explicit",
        "fully_distributed",
        "virtual_center",
        "integrated",
    )
    assert formulation_names(decomposed=False) == ("integrated",)
    assert formulation_names(rho_basis="hessian") == ("fully_distributed", "virtual_center")
    assert formulation_names(learned_start=True) == ("local_explicit",)
    assert formulation_info("integrated").n_rho(3) == 1
    assert formulation_info("local_explicit").n_rho(3) == 3
    T = random_problem(0, 2).topology
    for name in FORMULATIONS:
        solver = formulation(name, T)
        assert formulation_info(solver) is type(solver).info
        assert solver.n_rho == formulation_info(name).n_rho(T.n_objectives)
    with pytest.raises(ValueError, match=r"formulation: expected one of \['local_explicit'"):
        check_formulation("admm")
    with pytest.raises(TypeError, match="unknown trait 'fast'"):
        formulation_names(fast=True)


def test_registration_is_checked():
    with pytest.raises(ValueError, match="'local_explicit' is taken by LocalExplicit"):
        register_formulation(type("Other", (LocalExplicit,), {"info": LocalExplicit.info}))
    with pytest.raises(TypeError, match="declares no FormulationInfo of its own"):
        register_formulation(type("Bare", (LocalExplicit,), {}))
    with pytest.raises(TypeError, match="expected an ADMMSolver subclass"):
        register_formulation(dict)
    with pytest.raises(ValueError, match="name: expected an identifier other than 'none'"):
        FormulationInfo(name="none", title="t", label="t")
    with pytest.raises(ValueError, match="rho: expected one of"):
        FormulationInfo(name="x", title="t", label="t", rho="two")
    assert tuple(FORMULATIONS)[0] == "local_explicit"  # nothing was registered


def test_a_new_formulation_runs_through_solve_sweep_and_simulate(toy, tmp_path, capsys):
    # every list of formulations follows the registry
    assert toy in formulation_names() and toy in loop_formulations()
    assert toy in formulation_names(decomposed=True, closed_loop=True)
    # the Python API: the same iterates as Local Explicit with the same options
    p = random_problem(1, 2, shared="all")
    T, data = p.topology, p.data()
    mine = jax.jit(formulation(toy, T).solve)(data)
    ref = jax.jit(LocalExplicit(T, kkt="dense", rho_method="power", finish="none").solve)(data)
    np.testing.assert_array_equal(np.asarray(mine.u), np.asarray(ref.u))
    assert int(mine.iterations) == int(ref.iterations)
    # ampc solve: a choice of --formulation, its rho per objective named
    assert main(["solve", "cruise_control", "--formulation", toy, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["formulation"] == toy and out["status"] == "solved"
    assert set(out["rho"]) == {"LST", "YRT"}
    # ampc sweep: its batched KKT form is the one it declares; a loop family takes it
    spec = SweepSpec(family="cruise_step", cases=4, rho=(1.0,), formulation=toy)
    from ampc_jax.sweep.run import _solver

    assert _solver(spec, T).kkt == "dense"
    SweepSpec(family="cruise_lane_change", cases=1, rho=(1.0,), formulation=toy)
    args = ["--family", "cruise_step", "--cases", "4", "--rho", "1", "--chunk", "4"]
    sweep = tmp_path / "sweep"
    assert (
        main(["sweep", *args, "--formulation", toy, "--quiet", "--no-figures", "--out", str(sweep)])
        == 0
    )
    tab = pq.read_table(sweep / "sweep.parquet").to_pydict()
    assert set(tab["formulation"]) == {toy} and all(tab["converged"])
    # ampc simulate: the controller of a closed loop, its rho defaults by its basis
    cfg = SimConfig(formulation=toy)
    assert cfg.rho_scale == SimConfig().rho_scale
    sim = tmp_path / "sim"
    argv = ["simulate", "cruise_lane_change", "--formulation", toy, "--duration", "0.5"]
    assert main([*argv, "--no-shadow", "--quiet", "--out", str(sim)]) == 0
    assert f"cruise_lane_change, {toy}," in capsys.readouterr().out
    metrics = json.loads((sim / "metrics.json").read_text())
    assert metrics["formulation"] == toy and metrics["fallbacks"] == 0


def test_an_unregistered_formulation_is_refused_everywhere(toy):
    unregister_formulation(toy)
    with pytest.raises(ValueError, match="formulation: expected one of"):
        SimConfig(formulation=toy)
    with pytest.raises(ValueError, match="formulation: expected one of"):
        SweepSpec(family="cruise_step", cases=4, rho=(1.0,), formulation=toy)
    register_formulation(ToyExplicit)  # the fixture removes it again
