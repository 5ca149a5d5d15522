"""A user's own diagnosis effect: a learned smooth dependence of the rate on the water cut.

Use it without changing the project: put this folder on PYTHONPATH and name the class as
``module:Class``::

    PYTHONPATH=examples vfm diagnose field.parquet --model mm --out diag \
        --effects my_effects:WaterCutCurve

The protocol (see :mod:`vfm_core.effects`): a subclass of ``Effect`` with a ``name``, a
``parameters`` dict of ``Prior(mean, std, low, high, unit, meaning)`` (SI units; learned
per well, standardised, penalised by the Gaussian prior and clamped to the bounds) and one
or more hooks that return a tensor [W, N] (or [W, 1]), or None for "no change":
``area_factor``, ``gas_z``, ``slip``, ``critical_ratio``, ``output_factor``. Hooks get
``inputs`` (an ``EffectInputs``: u, p_up [Pa], p_down [Pa], t_up [K], eta_gas, eta_oil,
water_cut, theta, well_test, feature(name)) and ``p`` (parameter name -> value [W, 1]).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from vfm_core.effects import Effect, EffectInputs, Prior

__all__ = ["WaterCutCurve", "TemperatureScale"]

_KNOTS = 11  # water cut 0, 0.1, ..., 1.0


class WaterCutCurve(Effect):
    """The rate times exp(s(wc)), s piecewise linear in the water cut wc on knots 0, 0.1, ..., 1.

    Each knot value is a log-factor with prior N(0, 0.1^2) (a 10 % change is one standard
    deviation) and bounds +-1. All zero (the prior mean) leaves the model unchanged.
    A physical reading: emulsions or water-dependent liquid properties that the
    homogeneous model misses.
    """

    name = "water_cut_curve"
    description = "A learned smooth factor of the water cut (piecewise linear log-factor)."
    parameters = {
        f"log_factor_{k}": Prior(
            0.0, 0.1, -1.0, 1.0, "-", f"log rate factor at water cut {k / 10:.1f}"
        )
        for k in range(_KNOTS)
    }

    def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        values = torch.cat([p[f"log_factor_{k}"] for k in range(_KNOTS)], dim=-1)  # [W, K]
        position = inputs.water_cut.clamp(0.0, 1.0) * (_KNOTS - 1)  # [W, N]
        left = position.floor().clamp(max=_KNOTS - 2).long()
        weight = position - left
        v_left = torch.gather(values, 1, left)
        v_right = torch.gather(values, 1, left + 1)
        return torch.exp(v_left + weight * (v_right - v_left))

    def describe(self, values: Mapping[str, float]) -> str:
        text = ", ".join(
            f"{k / 10:.1f}: {100 * (pow(2.718281828, values[f'log_factor_{k}']) - 1):+.1f} %"
            for k in range(_KNOTS)
        )
        return f"Rate factor by water cut: {text}."


class TemperatureScale(Effect):
    """The smallest possible effect: rate times 1 + k (t_up - 60 degC)/10 K, k learned."""

    name = "temperature_scale"
    description = "A linear rate factor of the upstream temperature."
    parameters = {"k": Prior(0.0, 0.05, -0.5, 0.5, "1/(10 K)", "relative rate change per 10 K")}

    def output_factor(self, inputs: EffectInputs, p: dict[str, torch.Tensor]) -> torch.Tensor:
        return 1.0 + p["k"] * (inputs.t_up - 333.15) / 10.0
