"""Convert Equinor's Volve daily production report into the observation format.

The Volve file (``volve_daily_production.csv``, Equinor Open Data Licence, credit "Equinor
and the Volve licence partners") holds one row per well per day. Under its licence terms
the project keeps it out of this repository, so this module only *reads* it from where the
user keeps it and writes the converted observations wherever the user asks (never commit
them either).

Which rows are kept: producers only (``WELL_TYPE == "OP"`` and ``FLOW_KIND ==
"production"``) on full producing days (``ON_STREAM_HRS >= 23.9``; up to 25 h on the day
the clocks go back), with choke, wellhead pressure, choke pressure drop and wellhead
temperature present and positive (a non-positive pressure drop is counted as ``p_down >=
p_up``), and non-negative produced volumes that are not all zero.
Every removed row is counted under the first reason in :data:`REMOVAL_REASONS` that
applies; nothing is dropped silently.

Mapping of one kept row (pressures in the file are gauge, the observation format wants
absolute):

============  ===============================================================  =============
column        from the Volve columns                                           unit
============  ===============================================================  =============
time          ``DATEPRD`` (``07-Apr-14``) at 12:00 UTC, the middle of the day  ISO 8601 UTC
              the daily averages describe
well          ``NPD_WELL_BORE_NAME``                                           string
choke         ``AVG_CHOKE_SIZE_P / 100`` (rows outside 0..1 removed, no clip)  fraction 0..1
p_up          ``AVG_WHP_P + ATM_BAR``                                          bar absolute
p_down        ``AVG_WHP_P - DP_CHOKE_SIZE + ATM_BAR``                          bar absolute
t_up          ``AVG_WHT_P``                                                    degC
eta_gas       ``BORE_GAS_VOL * RHO_GAS_SC / m_total``                          mass fraction
eta_oil       ``BORE_OIL_VOL * RHO_OIL / m_total``                             mass fraction
q_oil         ``BORE_OIL_VOL / ON_STREAM_HRS``                                 Sm3/h
q_gas         ``BORE_GAS_VOL / ON_STREAM_HRS``                                 Sm3/h
q_water       ``BORE_WAT_VOL / ON_STREAM_HRS``                                 Sm3/h
q_total       ``q_oil + q_gas + q_water``                                      Sm3/h
source        ``mpfm``                                                         -
============  ===============================================================  =============

with the day's mass ``m_total = BORE_OIL_VOL*RHO_OIL + BORE_GAS_VOL*RHO_GAS_SC +
BORE_WAT_VOL*RHO_WAT`` (kg per day; only the ratios matter). The densities are assumptions,
not data from the file (see the constants). The daily volumes are allocated from facility
totals and well tests rather than metered per well; they are labelled ``mpfm`` because they
play the part of a multiphase-meter target, with an error of their own.

What the data are, seen by an engineer (:func:`field_notes` prints it at import):

- **Allocation.** On nearly every day with more than one well producing, every well's
  gas-oil ratio is the same (the field's, within 0.04 % at the median): the gas, 98 % of
  ``q_total`` at standard conditions, is the allocated oil times a field-wide GOR, not a
  per-well measurement. ``q_total`` is therefore (1 + field GOR) times the allocated oil
  plus the water; no well-level input explains the field GOR's day-to-day moves.
- **Densities.** The file has volumes only; the mass fractions need densities, which are
  assumptions. They are the project's prior means (:data:`vfm_core.physics.PRIORS`), so
  that the phase split of :func:`vfm_core.learning.streaming.phase_split` at those densities (what
  every model without learned densities uses) gives back exactly the day's phase shares:
  with other densities the split would carry a bias of their ratio into the phases.
- **The choke wide open.** Some wells spend most of their late life with the choke fully
  open and well under 1 bar across it (15/9-F-12 from mid 2015, 15/9-F-5 throughout):
  the choke does not restrict the flow there, the rate is set by the reservoir and the
  tubing, and a choke model that reads the rate from a pressure drop at the resolution of
  the gauges cannot work. ``min_choke_dp_bar`` (``vfm import-volve --min-choke-dp 1``)
  removes such days, counted under their own reason; by default they are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vfm_core import physics, schema, units
from vfm_core.errors import DataError
from vfm_core.observations import save_observations

__all__ = [
    "RHO_OIL",
    "RHO_WAT",
    "M_GAS",
    "RHO_GAS_SC",
    "MIN_ON_STREAM_HOURS",
    "MAX_ON_STREAM_HOURS",
    "NEEDED_COLUMNS",
    "REMOVAL_REASONS",
    "ImportReport",
    "field_notes",
    "read_volve_csv",
    "convert_volve",
    "import_volve",
]

#: Assumed stock-tank oil density, kg/m3: the project's prior mean, a light North Sea crude.
#: An assumption (the file carries no densities); it sets only the mass fractions, and
#: matching the prior makes the phase split at prior densities return the day's shares.
RHO_OIL = physics.PRIORS["rho_oil"].mean
#: Assumed produced-water density, kg/m3: the project's prior mean (saline water).
RHO_WAT = physics.PRIORS["rho_wat"].mean
#: Assumed gas molar mass, kg/mol: the mean of the project's prior.
M_GAS = physics.PRIORS["m_gas"].mean
#: Gas density at standard conditions (101325 Pa, 288.15 K) for :data:`M_GAS`, kg/m3.
RHO_GAS_SC = float(physics.gas_density_standard(M_GAS))
#: A day counts as a full producing day from this many hours on stream, h.
MIN_ON_STREAM_HOURS = 23.9
#: No day is longer than this (25 h on the day the clocks go back in October), h.
MAX_ON_STREAM_HOURS = 25.0

_DATE = "DATEPRD"
_WELL = "NPD_WELL_BORE_NAME"
_HOURS = "ON_STREAM_HRS"
_CHOKE = "AVG_CHOKE_SIZE_P"
_WHP = "AVG_WHP_P"
_DP = "DP_CHOKE_SIZE"
_WHT = "AVG_WHT_P"
_OIL = "BORE_OIL_VOL"
_GAS = "BORE_GAS_VOL"
_WAT = "BORE_WAT_VOL"
_FLOW_KIND = "FLOW_KIND"
_WELL_TYPE = "WELL_TYPE"
_DATE_FORMAT = "%d-%b-%y"

_INPUTS = (_CHOKE, _WHP, _DP, _WHT)
_VOLUMES = (_OIL, _GAS, _WAT)
_NUMERIC = (_HOURS, *_INPUTS, *_VOLUMES)
#: The raw columns the conversion reads; any others are ignored.
NEEDED_COLUMNS: tuple[str, ...] = (_DATE, _WELL, _WELL_TYPE, _FLOW_KIND, *_NUMERIC)

_NOT_PRODUCER = "not a producer (WELL_TYPE is not OP or FLOW_KIND is not production)"
_NO_ID = "no usable date or well (DATEPRD not like 07-Apr-14, or NPD_WELL_BORE_NAME empty)"
_PART_DAY = f"not a full producing day (ON_STREAM_HRS < {MIN_ON_STREAM_HOURS:g})"
_LONG_DAY = f"ON_STREAM_HRS above {MAX_ON_STREAM_HOURS:g} (longer than any day)"
_MISSING_INPUT = "missing choke/pressure/temperature"
_NONPOSITIVE_INPUT = "choke, wellhead pressure or wellhead temperature not positive"
_CHOKE_RANGE = "choke outside 0..1 (AVG_CHOKE_SIZE_P above 100 %)"
_MISSING_VOLUME = "missing produced volume (BORE_OIL_VOL, BORE_GAS_VOL or BORE_WAT_VOL empty)"
_NEGATIVE_VOLUME = "negative produced volume"
_NO_VOLUME = "no produced volume"
_P_DOWN_NONPOSITIVE = "p_down <= 0 (DP_CHOKE_SIZE exceeds the absolute wellhead pressure)"
_P_DOWN_NOT_BELOW = "p_down >= p_up (DP_CHOKE_SIZE not positive)"
_DUPLICATE = "duplicate well and day (the first is kept)"
_LOW_DP = (
    "choke pressure drop below the minimum asked for (--min-choke-dp): the choke does not "
    "restrict the flow"
)

#: Why rows are removed, in the order they are tested; a row counts under the first that applies.
REMOVAL_REASONS: tuple[str, ...] = (
    _NOT_PRODUCER,
    _NO_ID,
    _PART_DAY,
    _LONG_DAY,
    _MISSING_INPUT,
    _NONPOSITIVE_INPUT,
    _CHOKE_RANGE,
    _MISSING_VOLUME,
    _NEGATIVE_VOLUME,
    _NO_VOLUME,
    _P_DOWN_NONPOSITIVE,
    _P_DOWN_NOT_BELOW,
    _DUPLICATE,
    _LOW_DP,
)


def _require_columns(frame: pd.DataFrame, where: str) -> None:
    missing = [c for c in NEEDED_COLUMNS if c not in frame.columns]
    if missing:
        raise DataError(
            f"{where} lacks the column(s) {', '.join(missing)} that the Volve conversion "
            "needs; give the daily production report (volve_daily_production.csv) with its "
            "original header."
        )


def _numeric_columns(frame: pd.DataFrame, where: str) -> pd.DataFrame:
    """The numeric Volve columns as float64; a cell that is not a number raises DataError."""
    out = {}
    for column in _NUMERIC:
        values = frame[column]
        if pd.api.types.is_numeric_dtype(values) and not pd.api.types.is_bool_dtype(values):
            out[column] = values.astype("float64")
            continue
        # Strings may still carry thousands separators ("1,166") when built by hand.
        text = values.astype("string").str.replace(",", "", regex=False).str.strip()
        number = pd.to_numeric(text.replace("", pd.NA), errors="coerce")
        bad = number.isna() & text.replace("", pd.NA).notna()
        if bad.any():
            position = int(np.flatnonzero(bad.to_numpy())[0])
            raise DataError(
                f"{where}: column {column} holds {values.iloc[position]!r} on row "
                f"{position + 2} (header = row 1), which is not a number; fix or empty that cell."
            )
        out[column] = number.astype("float64")
    return pd.DataFrame(out, index=frame.index)


def read_volve_csv(path: str | Path) -> pd.DataFrame:
    """Read Volve's daily production CSV as it is, with numbers as float64 (NaN where empty).

    Quoted thousands separators (``"1,166"``) are parsed as numbers. Raises
    :class:`DataError` naming the file when it is missing or unreadable, or when a column
    the conversion needs (:data:`NEEDED_COLUMNS`) is absent or holds text.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(
            f"Volve file {path} not found; give the path of volve_daily_production.csv "
            "(it is licensed and kept outside the repository, e.g. ../shared/data/volve/)."
        )
    text_columns = {_DATE: "string", _WELL: "string", _WELL_TYPE: "string", _FLOW_KIND: "string"}
    try:
        raw = pd.read_csv(
            path,
            thousands=",",
            dtype=text_columns,
            keep_default_na=False,
            na_values=[""],
            encoding="utf-8",
        )
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, OSError) as exc:
        raise DataError(f"Volve file {path} cannot be read as CSV: {exc}.") from exc
    where = f"Volve file {path}"
    _require_columns(raw, where)
    raw[list(_NUMERIC)] = _numeric_columns(raw, where)
    return raw


def convert_volve(
    raw: pd.DataFrame, *, min_choke_dp_bar: float = 0.0
) -> tuple[pd.DataFrame, dict[str, int]]:
    """Turn raw Volve rows into observations (see the module table for the mapping).

    Returns the observation frame (sorted by time, then well, with the optional ``q_gas``,
    ``q_oil`` and ``q_water`` columns) and, for every reason in :data:`REMOVAL_REASONS`,
    how many rows were removed for it (zero included), so that ``len(raw) ==
    len(frame) + sum(removed.values())``. ``raw`` is not modified. ``min_choke_dp_bar``
    (bar, default 0: keep every day) removes the days whose choke pressure drop is below
    it, where the choke does not restrict the flow (see the module docstring).
    """
    if not (np.isfinite(min_choke_dp_bar) and min_choke_dp_bar >= 0):
        raise DataError(
            f"The minimum choke pressure drop {min_choke_dp_bar!r} bar is not a number of at "
            "least 0; give e.g. --min-choke-dp 1."
        )
    _require_columns(raw, "The Volve frame")
    num = _numeric_columns(raw, "The Volve frame")
    well = raw[_WELL].astype("string").str.strip()
    day = pd.to_datetime(
        raw[_DATE].astype("string").str.strip(), format=_DATE_FORMAT, errors="coerce"
    )
    time = day.dt.tz_localize("UTC") + pd.Timedelta(hours=12)

    hours = num[_HOURS]
    inputs = num[list(_INPUTS)]
    volumes = num[list(_VOLUMES)]
    choke = num[_CHOKE] / 100.0
    p_up = num[_WHP] + units.ATM_BAR
    p_down = num[_WHP] - num[_DP] + units.ATM_BAR

    is_producer = (raw[_WELL_TYPE].astype("string").str.strip() == "OP") & (
        raw[_FLOW_KIND].astype("string").str.strip() == "production"
    )
    failures: dict[str, pd.Series] = {
        _NOT_PRODUCER: ~is_producer.fillna(False).astype(bool),
        _NO_ID: time.isna() | well.isna() | (well == ""),
        # NaN compares False, so a missing ON_STREAM_HRS is not a full producing day either.
        _PART_DAY: ~(hours >= MIN_ON_STREAM_HOURS),
        _LONG_DAY: hours > MAX_ON_STREAM_HOURS,
        _MISSING_INPUT: ~np.isfinite(inputs).all(axis=1),
        # A non-positive DP_CHOKE_SIZE is caught below, as p_down >= p_up.
        _NONPOSITIVE_INPUT: (num[[_CHOKE, _WHP, _WHT]] <= 0).any(axis=1),
        _CHOKE_RANGE: (choke < 0) | (choke > 1),
        _MISSING_VOLUME: ~np.isfinite(volumes).all(axis=1),
        _NEGATIVE_VOLUME: (volumes < 0).any(axis=1),
        _NO_VOLUME: volumes.sum(axis=1) <= 0,
        _P_DOWN_NONPOSITIVE: p_down <= 0,
        _P_DOWN_NOT_BELOW: p_down >= p_up,
    }
    keep, removed = _sift(failures, time, well, num[_DP], min_choke_dp_bar)
    return _observations(
        keep,
        time=time,
        well=well,
        inputs={"choke": choke, "p_up": p_up, "p_down": p_down, "t_up": num[_WHT]},
        hours=hours,
        volumes=volumes,
    ), removed


def _sift(
    failures: dict[str, pd.Series],
    time: pd.Series,
    well: pd.Series,
    dp_bar: pd.Series,
    min_choke_dp_bar: float,
) -> tuple[pd.Series, dict[str, int]]:
    """The rows kept, and how many rows each reason removed: every row is counted under
    the first reason it fails (in the order of ``failures``), then the repeated (time,
    well) pairs, then the days whose choke pressure drop ``dp_bar`` is below the minimum."""
    keep = pd.Series(True, index=time.index)
    removed: dict[str, int] = {}
    for reason, failed in failures.items():
        hit = keep & failed.fillna(False).astype(bool)
        removed[reason] = int(hit.sum())
        keep &= ~hit
    duplicate = keep & pd.DataFrame({"t": time, "w": well})[keep].duplicated().reindex(
        time.index, fill_value=False
    )
    removed[_DUPLICATE] = int(duplicate.sum())
    keep &= ~duplicate
    low_dp = keep & (dp_bar < min_choke_dp_bar)
    removed[_LOW_DP] = int(low_dp.sum())
    keep &= ~low_dp
    return keep, removed


def _observations(
    keep: pd.Series,
    *,
    time: pd.Series,
    well: pd.Series,
    inputs: dict[str, pd.Series],
    hours: pd.Series,
    volumes: pd.DataFrame,
) -> pd.DataFrame:
    """The kept rows as observations: the choke inputs (``inputs``: choke fraction, bar a,
    bar a, degC), the mass fractions from the day's volumes and the standard densities,
    and the rates (Sm3/h: the day's volumes over its hours on stream), sorted by time
    then well."""
    kept_hours = hours[keep]
    oil, gas, wat = (volumes.loc[keep, c] for c in _VOLUMES)
    mass_oil = oil * RHO_OIL
    mass_gas = gas * RHO_GAS_SC
    mass_total = mass_oil + mass_gas + wat * RHO_WAT
    q_oil = oil / kept_hours
    q_gas = gas / kept_hours
    q_water = wat / kept_hours
    frame = pd.DataFrame(
        {
            schema.TIME: time[keep],
            schema.WELL: well[keep].astype(str),
            **{name: values[keep] for name, values in inputs.items()},
            "eta_gas": mass_gas / mass_total,
            "eta_oil": mass_oil / mass_total,
            schema.TARGET: q_oil + q_gas + q_water,
            schema.SOURCE: schema.MPFM,
            "q_gas": q_gas,
            "q_oil": q_oil,
            "q_water": q_water,
        }
    )
    return frame.sort_values([schema.TIME, schema.WELL], kind="stable").reset_index(drop=True)


@dataclass(frozen=True)
class ImportReport:
    """What :func:`import_volve` did: rows read and written, removals by reason, rows per well."""

    n_read: int
    n_written: int
    removed: dict[str, int]
    wells: dict[str, int]
    out: Path
    #: what an engineer should know about these data (see :func:`field_notes`)
    notes: tuple[str, ...] = ()

    def summary(self) -> str:
        """A short human-readable account, one fact per line."""
        lines = [
            f"Read {self.n_read:,} Volve rows; wrote {self.n_written:,} observations "
            f"of {len(self.wells)} wells to {self.out}.",
            f"Removed {sum(self.removed.values()):,} rows:",
        ]
        lines += [f"  {n:>7,}  {reason}" for reason, n in self.removed.items() if n]
        lines.append("Rows per well:")
        lines += [f"  {n:>7,}  {name}" for name, n in self.wells.items()]
        if self.notes:
            lines.append("Before you model these data:")
            lines += [f"  - {note}" for note in self.notes]
        return "\n".join(lines)


#: A well's GOR counts as the field's when within this relative distance of the day's median.
_SAME_GOR = 0.005
#: Below this choke pressure drop (bar) the choke hardly restricts the flow.
_LOW_DP_BAR = 1.0


def field_notes(frame: pd.DataFrame) -> tuple[str, ...]:
    """What the converted observations say about how they were made (plain sentences).

    The share of days (with more than one well on stream and some oil) on which a well's
    gas-oil ratio equals the day's field median within 0.5 % (allocation by a field GOR);
    the gas share of ``q_total``; and per well the share of days with the choke fully
    open (>= 99 %) and with less than 1 bar across it.
    """
    notes: list[str] = []
    if frame.empty:
        return ()
    oil = frame["q_oil"].to_numpy(dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        gor = pd.Series(frame["q_gas"].to_numpy(dtype=float) / oil, index=frame.index)
    gor = gor.where(oil > 0)
    day = frame[schema.TIME]
    several = gor.groupby(day).transform("count") > 1
    field = gor.groupby(day).transform("median")
    same = ((gor / field - 1.0).abs() <= _SAME_GOR)[several & gor.notna()]
    if len(same):
        notes.append(
            f"On {same.mean() * 100:.0f} % of the well-days with other wells on stream, the "
            f"well's gas-oil ratio is the field's of that day (within {_SAME_GOR * 100:g} %): "
            "the gas is allocated from the oil with a field-wide GOR, not measured per well."
        )
    gas_share = float(np.median(frame["q_gas"] / frame[schema.TARGET]))
    notes.append(
        f"Gas is {gas_share * 100:.0f} % of q_total (standard conditions, median): score "
        "q_oil and q_water too (vfm evaluate does, where the data have them)."
    )
    dp = frame["p_up"] - frame["p_down"]
    for well, g in frame.groupby(schema.WELL, sort=True):
        full = g["choke"] >= 0.99
        low = float((dp[g.index] < _LOW_DP_BAR).mean())
        if full.mean() < 0.25 and low < 0.1:
            continue
        text = f"{well}: choke fully open on {full.mean() * 100:.0f} % of its days"
        if full.any():
            text += f" (median {float(dp[g.index][full].median()):.1f} bar across it then)"
        if low >= 0.1:
            text += (
                f", less than {_LOW_DP_BAR:g} bar across it on {low * 100:.0f} %: there the "
                "choke does not restrict the flow, and a choke model has nothing to read the "
                "rate from"
            )
        else:
            text += (
                ": a linear valve characteristic is unlikely to hold up to full opening; "
                "check it with vfm diagnose (candidate valve)"
            )
        notes.append(text + ".")
    return tuple(notes)


def import_volve(
    src: str | Path, out: str | Path, *, min_choke_dp_bar: float = 0.0
) -> ImportReport:
    """Read the Volve CSV at ``src``, convert it and write observations to ``out``.

    ``out`` ends in ``.csv`` or ``.parquet``. The output is derived from licensed data:
    keep it outside the repository (or ignored by git). Raises :class:`DataError` when the
    source cannot be used. ``min_choke_dp_bar``: see :func:`convert_volve`.
    """
    raw = read_volve_csv(src)
    frame, removed = convert_volve(raw, min_choke_dp_bar=min_choke_dp_bar)
    written = save_observations(frame, out)
    per_well = frame[schema.WELL].value_counts().sort_index()
    return ImportReport(
        n_read=len(raw),
        n_written=len(frame),
        removed=removed,
        wells={str(name): int(n) for name, n in per_well.items()},
        out=Path(written),
        notes=field_notes(frame),
    )
