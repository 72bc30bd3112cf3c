"""The learned start (ampc_jax.admm.learned_start): the formulation's own solution
(against Clarabel), the previous-step warm start kept by an untrained "loop"
network, a start at the optimum a fixed point, schedules and refused inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ampc_jax.admm.learned_start import (
    SCHEDULE_MAX,
    LearnedStart,
    StartModel,
    box_coordinates,
    n_features,
)
from ampc_jax.formulations import PAPER_ITERATION, formulation
from ampc_jax.sweep import family
from ampc_jax.tuning.solver import reference_inputs

jax.config.update("jax_enable_x64", True)


@pytest.fixture(scope="module")
def cases():
    c = family("cruise_step").sample(3, seed=5, groups="full", dtype=jnp.float64)
    inner = formulation(
        "local_explicit", c.topology, anderson=3, max_iter=2000, **PAPER_ITERATION
    )  # the iteration the start is trained on
    return c, inner


def _case(c, i):
    return jax.tree.map(lambda x: x[i], c.data)


def _model(kind, inner, data, *, hidden=(5,), zero_last=False, out_mean=None, schedule=0, seed=0):
    """A small random network of ``kind`` for ``inner``'s problem (NumPy weights)."""
    rng = np.random.default_rng(seed)
    n_point = int(np.size(inner.point(inner.cold_state())))
    n_f = n_features(data)
    T = inner.topology
    n_in = n_f + (n_point if kind == "loop" else 0)
    n_out = n_point if kind == "loop" else T.horizon * T.n_u
    sizes = [n_in, *hidden, n_out]
    layers = []
    for k, (a, b) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        last = k == len(sizes) - 2
        W = np.zeros((a, b)) if last and zero_last else 0.3 * rng.standard_normal((a, b))
        layers.append((W, 0.1 * rng.standard_normal(b) * (not (last and zero_last))))
    J = T.n_objectives
    return StartModel(
        kind=kind,
        layers=tuple(layers),
        input_mean=np.zeros(n_in),
        input_scale=np.full(n_in, 100.0),
        out_mean=np.zeros(n_out) if out_mean is None else out_mean,
        out_scale=np.full(n_out, 0.1 if kind == "step" else 1.0),
        out_mask=np.ones(n_out),
        schedule_rho=np.full((schedule, J), 0.7),
        schedule_relaxation=np.full((schedule,), 1.3),
        n_point=n_point,
        objectives=T.objective_names,
        horizon=T.horizon,
    )


@pytest.mark.timeout(180)
def test_untrained_loop_network_is_the_previous_step_warm_start(cases):
    c, inner = cases
    d0, d1 = _case(c, 0), _case(c, 1)
    p = inner.params(relaxation=1.5, tol_primal=1.0, tol_dual=1.0)
    first = jax.jit(inner.solve)(d0, p)
    warm = inner.shift(first.state)
    model = _model("loop", inner, d1, hidden=(7, 4), zero_last=True)
    learned = LearnedStart(inner, model)
    a = jax.jit(inner.solve)(d1, p, warm)
    b = jax.jit(learned.solve)(d1, p, warm)
    assert int(a.iterations) == int(b.iterations) > 0
    np.testing.assert_array_equal(np.asarray(a.u), np.asarray(b.u))
    for x, y in zip(jax.tree.leaves(a.state), jax.tree.leaves(b.state), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # a trained (non-zero) last layer does move the start: the test can fail
    moved = LearnedStart(inner, _model("loop", inner, d1, hidden=(7, 4)))
    s0 = moved.init(moved.setup(d1, p), warm)
    assert not np.array_equal(np.asarray(inner.point(s0)), np.asarray(inner.point(warm)))


@pytest.mark.timeout(240)
# with a schedule in the default run (it includes the plain start's path after k)
@pytest.mark.parametrize("schedule", [pytest.param(0, marks=pytest.mark.slow), 3])
def test_learned_start_reaches_the_formulations_own_solution(cases, schedule):
    c, inner = cases
    u_ref = reference_inputs(c.topology, c.data)  # Clarabel on the condensed QP
    p = inner.params(rho=(1.0, 0.5), relaxation=1.5, tol_primal=1e-10, tol_dual=1e-10)
    learned = LearnedStart(inner, _model("step", inner, _case(c, 0), schedule=schedule))
    own = jax.jit(jax.vmap(inner.solve, in_axes=(0, None)))(c.data, p)
    got = jax.jit(jax.vmap(learned.solve, in_axes=(0, None)))(c.data, p)
    assert np.all(np.asarray(own.converged)) and np.all(np.asarray(got.converged))
    scale = np.max(np.abs(u_ref)) + 1.0
    np.testing.assert_allclose(np.asarray(got.u), np.asarray(own.u), atol=1e-6 * scale)
    np.testing.assert_allclose(np.asarray(got.u), u_ref, atol=1e-5 * scale)
    it_own, it_got = np.asarray(own.iterations), np.asarray(got.iterations)
    assert not np.array_equal(it_own, it_got)  # only the path changes
    assert np.all(it_got >= schedule)  # the scheduled iterations count


@pytest.mark.timeout(180)
def test_a_start_at_the_optimum_is_a_fixed_point(cases):
    c, _ = cases
    inner = formulation("local_explicit", c.topology, max_iter=20000, **PAPER_ITERATION)
    d = _case(c, 2)
    deep = inner.params(tol_primal=1e-22, tol_dual=1e-22)
    u_star = jax.jit(inner.solve)(d, deep).u
    t = np.asarray(box_coordinates(u_star, d)).ravel()
    model = _model("step", inner, d, zero_last=True, out_mean=t)
    model = StartModel(**{**_fields(model), "out_scale": np.ones(t.size)})
    learned = LearnedStart(inner, model)
    p = inner.params(tol_primal=1.0, tol_dual=1.0)
    setup = learned.setup(d, p)
    s0 = learned.init(setup)
    s1 = inner.step(setup.main, s0)
    x0, x1 = np.asarray(inner.point(s0)), np.asarray(inner.point(s1))
    assert np.linalg.norm(x1 - x0) <= 1e-6 * (np.linalg.norm(x0) + 1.0)
    np.testing.assert_allclose(
        np.asarray(inner.result(setup.main, s1).u), np.asarray(u_star), atol=1e-6 * 2000.0
    )
    at_opt = jax.jit(learned.solve)(d, p)
    cold = jax.jit(inner.solve)(d, p)
    assert bool(at_opt.converged) and int(at_opt.iterations) <= 2 < int(cold.iterations)


def _fields(m):
    names = (
        "kind layers input_mean input_scale out_mean out_scale out_mask schedule_rho "
        "schedule_relaxation n_point objectives horizon"
    ).split()
    return {k: getattr(m, k) for k in names}


@pytest.mark.slow  # shapes only; the scheduled solve is checked against Clarabel above
@pytest.mark.timeout(120)
def test_schedule_shapes(cases):
    c, inner = cases
    d = _case(c, 0)
    J = c.topology.n_objectives
    for k in (0, 1, 4):
        learned = LearnedStart(inner, _model("step", inner, d, schedule=k))
        setup = learned.setup(d, inner.params())
        assert learned.model.schedule_length == k
        if k == 0:
            assert setup.schedule is None
        else:
            assert all(x.shape[0] == k for x in jax.tree.leaves(setup.schedule))
            assert setup.arrays.schedule_rho.shape == (k, J)
    good = _fields(_model("step", inner, d, schedule=2))
    with pytest.raises(ValueError, match="schedule"):
        StartModel(**{**good, "schedule_rho": np.ones((2, J + 1))})
    with pytest.raises(ValueError, match="schedule"):
        StartModel(
            **{
                **good,
                "schedule_rho": np.ones((SCHEDULE_MAX + 1, J)),
                "schedule_relaxation": np.ones(SCHEDULE_MAX + 1),
            }
        )
    with pytest.raises(ValueError, match="schedule"):
        StartModel(**{**good, "schedule_relaxation": np.array([1.0, 2.5])})
    with pytest.raises(ValueError, match="schedule"):
        StartModel(**{**good, "schedule_rho": np.array([[1.0] * J, [-1.0] * J])})


@pytest.mark.timeout(120)
def test_bad_models_are_refused_naming_the_field(cases):
    c, inner = cases
    d = _case(c, 0)
    good = _fields(_model("step", inner, d))
    W0, b0 = good["layers"][0]
    bad = {
        "kind": {"kind": "magic"},
        r"layers\[0\]": {"layers": ((W0[:-1], b0), *good["layers"][1:])},
        "input_scale": {"input_scale": np.zeros_like(good["input_scale"])},
        "weights": {"out_mean": np.full_like(good["out_mean"], np.nan)},
        "out_mask": {"out_mask": np.ones(3)},
    }
    for field, change in bad.items():
        with pytest.raises(ValueError, match=field):
            StartModel(**{**good, **change})
    other = formulation("local_explicit", family("cruise_step").sample(1, horizon=3).topology)
    with pytest.raises(ValueError, match="warm_start"):
        LearnedStart(other, StartModel(**good))
    wrong_inputs = StartModel(
        **{
            **good,
            "layers": ((np.zeros((3, W0.shape[1])), b0), *good["layers"][1:]),
            "input_mean": np.zeros(3),
            "input_scale": np.ones(3),
        }
    )
    with pytest.raises(ValueError, match="warm_start"):
        LearnedStart(inner, wrong_inputs).setup(d, inner.params())
