"""The observation format: the one contract every tool reads and writes (CSV or Parquet).

One row is one steady-state sample of one well, with or without a measured rate.

============  =====================================================================  ===========
column        meaning                                                                unit
============  =====================================================================  ===========
time          when the steady-state sample was taken, ISO 8601, UTC                  -
well          well identifier                                                        string
choke         choke opening                                                          fraction 0..1
p_up          pressure upstream of the choke                                         bar absolute
p_down        pressure downstream of the choke                                       bar absolute
t_up          temperature upstream of the choke                                      degC
eta_gas       gas mass fraction of the mixture                                       0..1
eta_oil       oil mass fraction of the mixture (water = 1 - eta_gas - eta_oil)       0..1
q_total       measured total volumetric rate at standard conditions; empty if none   Sm3/h
source        ``mpfm`` or ``well_test``; empty where no measurement                   -
============  =====================================================================  ===========

Optional: ``q_gas``, ``q_oil``, ``q_water`` (Sm3/h). Extra columns are kept and ignored.
"""

from __future__ import annotations

__all__ = [
    "TIME",
    "WELL",
    "INPUT_COLUMNS",
    "TARGET",
    "SOURCE",
    "REQUIRED_COLUMNS",
    "OPTIONAL_RATE_COLUMNS",
    "SOURCES",
    "UNITS",
]

TIME = "time"
WELL = "well"
#: The six model inputs, in this order everywhere (the paper's x = (u, p1, p2, T1, eta_gas, eta_oil)).
INPUT_COLUMNS: tuple[str, ...] = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")
TARGET = "q_total"
SOURCE = "source"
REQUIRED_COLUMNS: tuple[str, ...] = (TIME, WELL, *INPUT_COLUMNS, TARGET, SOURCE)
OPTIONAL_RATE_COLUMNS: tuple[str, ...] = ("q_gas", "q_oil", "q_water")
MPFM = "mpfm"
WELL_TEST = "well_test"
SOURCES: tuple[str, ...] = (MPFM, WELL_TEST)

#: Unit of every numeric column at the file boundary.
UNITS: dict[str, str] = {
    "choke": "fraction 0..1",
    "p_up": "bar absolute",
    "p_down": "bar absolute",
    "t_up": "degC",
    "eta_gas": "mass fraction 0..1",
    "eta_oil": "mass fraction 0..1",
    "q_total": "Sm3/h",
    "q_gas": "Sm3/h",
    "q_oil": "Sm3/h",
    "q_water": "Sm3/h",
}
