"""The tuners' one training loop (ampc_jax.tuning.fit): what it keeps, what it records,
how it treats non-finite gradients and updates, and its spec's checks."""

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from ampc_jax.tuning.fit import FitSpec, Validation, fit

pytestmark = pytest.mark.timeout(60)


def _quadratic(th):
    return jnp.sum((th - 3.0) ** 2)


@pytest.mark.parametrize("options", [None, {"xla_backend_optimization_level": 0}])
def test_adam_steps_match_optax_and_the_best_point_is_kept(options):
    """Also with a closed loop's compiler options (what tune_solver compiles with)."""
    spec = FitSpec(steps=5, lr=0.1, progress=False, compiler_options=options)
    run = fit(_quadratic, jnp.zeros(2), spec)
    # the same steps by hand: the loss recorded is that of the point before each step
    opt = optax.adam(0.1)
    th, state, losses = jnp.zeros(2), opt.init(jnp.zeros(2)), []
    for _ in range(5):
        losses.append(float(_quadratic(th)))
        g = 2.0 * (th - 3.0)
        upd, state = opt.update(g, state, th)
        th = optax.apply_updates(th, upd)
    np.testing.assert_allclose([r["loss"] for r in run.history[:5]], losses, rtol=1e-12)
    assert [r["step"] for r in run.history] == [0, 1, 2, 3, 4, 5]  # and the final point
    np.testing.assert_allclose(np.asarray(run.last), np.asarray(th), rtol=1e-12)
    assert run.value == min(r["loss"] for r in run.history)
    np.testing.assert_allclose(np.asarray(run.theta), np.asarray(th), rtol=1e-12)


def test_batches_aux_and_non_finite_gradients():
    data = jnp.array([1.0, 2.0, jnp.nan, 4.0])

    def loss(th, idx):
        x = data[idx]
        v = jnp.mean(jnp.where(jnp.isfinite(x), (th - x) ** 2, th * x))
        return v, {"n": idx.shape[0]}

    seen = []
    run = fit(
        loss,
        jnp.array(0.0),
        FitSpec(3, 0.5, finite_grads=True, finite_updates=True, progress=False),
        has_aux=True,
        batches=lambda k: jnp.array([k % 4, 3]),
        record=lambda k, th, v, aux: seen.append(int(aux["n"])) or {"step": k},
    )
    assert seen == [2, 2, 2, 2] and np.isfinite(float(run.last))  # step 2 read the NaN


def test_validation_and_last_selection():
    scores = iter([5.0, 1.0, 3.0])
    hist = []
    val = Validation(lambda th: next(scores), 2, lambda k, s: {"phase": "val", "step": k, "s": s})
    run = fit(
        _quadratic,
        jnp.zeros(1),
        FitSpec(4, 0.1, 0.05, progress=False),
        validation=val,
        history=hist,
    )
    assert [h["step"] for h in hist if h.get("phase") == "val"] == [0, 2, 4]
    assert run.value == 1.0 and run.history == hist
    last = fit(_quadratic, jnp.zeros(1), FitSpec(3, 0.1, progress=False), select="last")
    np.testing.assert_array_equal(np.asarray(last.theta), np.asarray(last.last))
    none = fit(_quadratic, jnp.zeros(1), FitSpec(0, 0.1))
    assert none.history == [] and float(none.theta[0]) == 0.0


@pytest.mark.parametrize(
    "kw, field",
    [
        ({"steps": -1, "lr": 0.1}, "steps"),
        ({"steps": 1.5, "lr": 0.1}, "steps"),
        ({"steps": 1, "lr": float("nan")}, "lr"),
        ({"steps": 1, "lr": 0.0}, "lr"),
        ({"steps": 1, "lr": 0.1, "decay": 2.0}, "decay"),
    ],
)
def test_spec_names_the_field(kw, field):
    with pytest.raises(ValueError, match=f"^{field}: "):
        FitSpec(**kw)
    with pytest.raises(ValueError, match="^select: "):
        fit(_quadratic, jnp.zeros(1), FitSpec(1, 0.1), select="best")
