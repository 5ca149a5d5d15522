"""Unit conversions at the boundaries.

Files and messages use engineering units (bar absolute, degC, Sm3/h); everything inside
the physics is SI (Pa, K, kg/s, Sm3/s). Convert exactly once, at the boundary, with these.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:  # only for the types: this module imports neither at run time
    import numpy as np
    import torch

__all__ = [
    "PA_PER_BAR",
    "ATM_BAR",
    "KELVIN_OFFSET",
    "SECONDS_PER_HOUR",
    "bar_to_pa",
    "pa_to_bar",
    "degc_to_k",
    "k_to_degc",
    "per_s_to_per_h",
    "per_h_to_per_s",
]

PA_PER_BAR = 1.0e5
#: Standard atmosphere in bar, used to turn gauge into absolute pressure.
ATM_BAR = 1.01325
KELVIN_OFFSET = 273.15
SECONDS_PER_HOUR = 3600.0

#: a number, an array or a tensor: the conversion returns the same kind
T = TypeVar("T", float, "np.ndarray[Any, Any]", "torch.Tensor")


def bar_to_pa(p_bar: T) -> T:
    """Pressure in bar -> Pa."""
    return p_bar * PA_PER_BAR


def pa_to_bar(p_pa: T) -> T:
    """Pressure in Pa -> bar."""
    return p_pa / PA_PER_BAR


def degc_to_k(t_degc: T) -> T:
    """Temperature in degC -> K."""
    return t_degc + KELVIN_OFFSET


def k_to_degc(t_k: T) -> T:
    """Temperature in K -> degC."""
    return t_k - KELVIN_OFFSET


def per_s_to_per_h(rate_per_s: T) -> T:
    """A rate per second (e.g. Sm3/s) -> per hour (Sm3/h)."""
    return rate_per_s * SECONDS_PER_HOUR


def per_h_to_per_s(rate_per_h: T) -> T:
    """A rate per hour (e.g. Sm3/h) -> per second (Sm3/s)."""
    return rate_per_h / SECONDS_PER_HOUR
