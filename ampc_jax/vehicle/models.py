"""What the paper's two control models share (section "Examples on Vehicle Control").

Both examples are linear(-affine) prediction models re-linearised at every
control step from the measured state and the driver's steering, eq.eq_linear::

    X^(k+1) = A_d X^(k) + sum_i B_d(i) U_(i)^(k) + W_d

returned as a :class:`ControlModel` of plain arrays (pure JAX: jittable,
vmappable, keeping the measurement's dtype). The examples themselves are
:mod:`~ampc_jax.vehicle.cruise` and :mod:`~ampc_jax.vehicle.stability`;
:class:`ExampleSettings` is the base of their settings.

Deviations from the printed paper
---------------------------------
Each is an item of ``docs/paper-notes.md`` (numbered there; "item N" below);
``docs/vehicle.md`` gives the reasoning and ``tests/vehicle/`` pins every choice.

1. (item 1) ``C_LST = [1, 0, 0]`` and ``C_YRT = [0, 0, 1]``: the printed
   eq.CC_objective swaps them.  Always corrected (no literal reading exists:
   the printed pair would track a speed reference with the yaw rate).
2. (item 2) ``I_w`` is a wheel inertia of 1.6 kg m^2, not a track width.
3. (item 3) RTV yaw entry of eq.VSC_system is ``dt T_w / (I_z R_w)`` (same
   moment balance as eq.CC_system); ``T_z`` is undefined in the paper.
4. (item 4) The wheel-speed reference is an angular speed,
   ``omega_ref = v_x (1 + S) / R_w`` with ``S = +S_x,des`` while the driver
   drives (``T_DTR > 0``), ``S = -S_x,des`` while the driver brakes
   (``T_DTR < 0``: the desired braking slip is negative) and ``S = 0`` without
   driver torque.
5. (item 9) eq.CC_system's A_d holds the Jacobian of the body-frame coupling
   terms (``v_x' = r v_y``, ``v_y' = -r v_x``) but is applied to the absolute
   state, which doubles those terms.  The *corrected* form adds
   ``dt [-r0 v_y0, +r0 v_x0, 0]`` to W_d so the one-step prediction is exact at
   the operating point (it is the first-order Taylor model).  The *literal*
   form (``settings.literal=True``) keeps the paper's W_d = B_STR U_STR.
6. (item 20) eq.VSC_system's wheel rows omit the tyre's reaction ``-R_w F_x``
   on the wheel (``I_w omega' = T - R_w F_x``), so the literal model predicts
   that any driving torque accelerates the wheel without bound and WSC would
   cancel the driver's torque even without slip.  The *corrected* form adds
   ``-dt R_w F_x,est / I_w`` per rear wheel to W_d, with the measured
   (estimated) longitudinal tyre forces held over the horizon, the same way the
   paper holds the lateral forces F_y in B_STR U_STR.  The literal form
   (``settings.literal=True``) keeps W_d = B_DTR T_DTR + B_STR U_STR.
7. (item 11) TCR's bound [0, T_DTR] moves with the driver torque every step.
   When the driver brakes (T_DTR < 0) the printed interval is empty; TCR then
   lies in [T_DTR, 0], i.e. it may only reduce the *magnitude* of the driver's
   rear-axle torque towards zero (``bounds = [min(0, T), max(0, T)]``).
8. (item 21) The printed text of eq.CC_system_1 calls T_FDB-L "the right-front"
   torque; the matrix B_d(FDB) (first column uses delta_FL and -T_w) puts it on
   the left front.  U_FDB = [T_FL, T_FR].
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..validation import check_flag
from .params import VehicleParams

__all__ = [
    "ControlModel",
    "ExampleSettings",
    "fdb_columns",
    "settings_dataclass",
    "str_rows",
    "yaw_rate_reference",
]


class ControlModel(NamedTuple):
    """One control step's affine prediction model, eq.eq_linear.

    ``X^(k+1) = A X^(k) + sum_i B[i] U_(i)^(k) + w`` for k = 0..N_p-1, with the
    objectives' outputs ``C_j X`` tracking ``ref[j]`` at k = 1..N_p.
    """

    A: Array  # (n_x, n_x)  A_d
    B: tuple[Array, ...]  # per agent in AGENTS order, (n_x, n_u_i)  B_d(i)
    w: Array  # (n_x,) W_d, held constant over the horizon
    x0: Array  # (n_x,) X^(0)
    ref: tuple[Array, ...]  # per objective in OBJECTIVES order, (n_y_j,)
    lb: tuple[Array, ...]  # per agent (n_u_i,)
    ub: tuple[Array, ...]  # per agent (n_u_i,)


class ExampleSettings:
    """Base of an example's settings: weights, bounds and the prediction model's step.

    A frozen dataclass registered as a JAX pytree (:func:`settings_dataclass`):
    the fields in ``STATIC`` (``horizon``, a size; ``dt``, the prediction step;
    ``literal``, a model choice) are static, every other field is an array leaf,
    so the weights and bounds are arguments of a compiled closed loop (changed
    without recompiling, vmapped over, differentiated in forward mode). Subclasses list their
    fields' kinds in ``WEIGHTS`` (Q_j >= 0), ``INPUT_WEIGHTS`` (R_(i) > 0) and
    ``BOUNDS`` (Nm >= 0).
    """

    STATIC: ClassVar[tuple[str, ...]] = ("horizon", "dt", "literal")
    WEIGHTS: ClassVar[tuple[str, ...]] = ()
    INPUT_WEIGHTS: ClassVar[tuple[str, ...]] = ()
    BOUNDS: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in dataclasses.fields(cls))

    def replace(self, **changes: Any) -> Any:
        """A copy with some fields replaced (TypeError naming an unknown field)."""
        unknown = sorted(set(changes) - set(self.field_names()))
        if unknown:
            raise TypeError(
                f"{type(self).__name__}: unknown field(s) {unknown}; expected some of "
                f"{list(self.field_names())}"
            )
        return dataclasses.replace(self, **changes)

    def as_arrays(self, dtype: Any) -> Any:
        """The settings with every array leaf as a ``dtype`` array (what a compiled loop takes)."""
        return jax.tree.map(lambda x: jnp.asarray(x, dtype), self)

    def validate(self) -> Any:
        """Check the fields (ValueError naming the field); returns ``self``.

        ``horizon`` an integer >= 1; ``dt`` > 0; weights >= 0 (0 switches an
        objective's tracking off; negative is non-convex); input weights > 0 (a
        zero input weight leaves H_j singular); bounds >= 0 Nm; all finite;
        ``literal`` True or False. Python scalars only (settings holding arrays
        inside a compiled loop are not checked).
        """

        def number(name: str) -> float:
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                raise ValueError(f"{name}: expected a number, got {v!r}")
            v = float(v)
            if not math.isfinite(v):
                raise ValueError(f"{name}: expected a finite number, got {v!r}")
            return v

        h = self.horizon
        if isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1:
            raise ValueError(f"horizon: expected an integer N_p >= 1 (prediction steps), got {h!r}")
        if not number("dt") > 0:
            raise ValueError(f"dt: expected a positive prediction step in s, got {self.dt!r}")
        for name in self.WEIGHTS:
            if number(name) < 0:
                raise ValueError(
                    f"{name}: expected a weight >= 0 (a negative Q_j makes the QP non-convex), "
                    f"got {getattr(self, name)!r}"
                )
        for name in self.INPUT_WEIGHTS:
            if not number(name) > 0:
                raise ValueError(
                    f"{name}: expected a weight > 0 (R_(i) = 0 leaves the objectives' Hessians "
                    f"H_j singular, so eq.opt_ro's rho* is undefined), got {getattr(self, name)!r}"
                )
        for name in self.BOUNDS:
            if number(name) < 0:
                raise ValueError(
                    f"{name}: expected a torque bound >= 0 Nm, got {getattr(self, name)!r}"
                )
        check_flag(self.literal, "literal")
        return self


def settings_dataclass(cls: type) -> type:
    """Make ``cls`` (an :class:`ExampleSettings` subclass) a frozen dataclass and a
    JAX pytree whose ``STATIC`` fields are static and the others array leaves."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    meta = [n for n in names if n in cls.STATIC]
    jax.tree_util.register_dataclass(
        cls, data_fields=[n for n in names if n not in meta], meta_fields=meta
    )
    return cls


def yaw_rate_reference(
    v_x: Array, steer: Array, mu: Array, params: VehicleParams, v_min: float = 0.5
) -> Array:
    """Friction-limited target yaw rate of eq.CC_objective, shape ().

    ``r_ref = sign(delta) min(|v_x delta / (L + K_us v_x^2)|, mu g / v_x)``.
    The friction limit ``mu g / v`` uses ``v = max(|v_x|, v_min)`` so it stays
    finite at standstill (where the first term, -> 0, is the minimum anyway).
    """
    v_x = jnp.asarray(v_x)
    kin = v_x * steer / (params.L + params.K_us * v_x**2)
    lim = mu * params.g / jnp.maximum(jnp.abs(v_x), v_min)
    return jnp.sign(steer) * jnp.minimum(jnp.abs(kin), lim)


def fdb_columns(delta: Array, params: VehicleParams) -> tuple[Array, Array, Array]:
    """Per-Nm effect of FL/FR brake torque on (v_x', v_y', r'), each shape (2,)."""
    p = params
    d = delta[:2]
    c, s = jnp.cos(d), jnp.sin(d)
    vx = c / (p.m * p.R_w)
    vy = s / (p.m * p.R_w)
    sign = jnp.array([-1.0, 1.0])  # FL at y = +T_w/2, FR at y = -T_w/2
    r = (2.0 * p.a * s + sign * p.T_w * c) / (2.0 * p.I_z * p.R_w)
    return vx, vy, r


def str_rows(delta: Array, params: VehicleParams) -> tuple[Array, Array, Array]:
    """Per-N effect of the four lateral tyre forces on (v_x', v_y', r'), each (4,)."""
    p = params
    c, s = jnp.cos(delta), jnp.sin(delta)
    vx = -s / p.m
    vy = c / p.m
    sign = jnp.array([1.0, -1.0, 1.0, -1.0])  # +T_w/2 sin for left wheels
    xw = jnp.array([p.a, p.a, -p.b, -p.b])
    r = (xw * c + sign * 0.5 * p.T_w * s) / p.I_z
    return vx, vy, r
