"""Read, check and write observation files (CSV or Parquet), the format of ``vfm_core.schema``.

Every tool that reads observations goes through :func:`load_observations` (files) or
:func:`validate_frame` (frames already in memory, e.g. from the service or replay), so all
of them see the same checked, typed and time-ordered data. :func:`save_observations`
writes the format back, atomically.

What a loaded frame holds:

* ``time``: ``datetime64[ns, UTC]``. Times are ISO 8601 text (CSV) or timestamps
  (Parquet). Times with an offset or zone are converted to UTC; times without one
  (naive times) are taken to be UTC already.
* ``well`` and ``source``: strings (surrounding whitespace removed); ``source`` is
  ``"mpfm"``, ``"well_test"`` or ``""`` where there is no measurement.
* the six inputs, ``q_total`` and any of the optional ``q_gas``/``q_oil``/``q_water``:
  float64 in the units of ``schema.UNITS``, NaN where the cell is empty.
* any other column, kept as it was read and otherwise ignored.
* rows sorted by (time, well) with a stable sort, index 0..n-1.
* separator readings (``source`` = ``separator``, ``well`` = the separator's name, inputs
  empty) are not in ``frame``: they are checked and returned apart, in
  ``LoadResult.separators`` (see :mod:`vfm_core.separator_format`, which also says how a
  reading counts the wells' samples and shut-in wells); an optional ``separator`` column on
  the wells' rows, or the ``separators`` mapping (well -> separator), says which wells flow
  into which separator.

Row numbers in messages count the header as row 1, so the first data row is row 2. In a
CSV file without blank lines or quoted line breaks this is the line number. For Parquet
files and in-memory frames the same rule is used: data row ``i`` (0-based) is row ``i + 2``.

Problems come in two kinds:

* Hard errors raise :class:`~vfm_core.errors.ObservationFormatError` naming the file, the
  first offending row, the column and the value, and how many other rows share the
  problem: a missing required column, text in a numeric column, a time that is not ISO
  8601 (or lies outside 1677..2262), an empty well id, an unknown ``source``.
* Physically illogical rows are removed (as the data of the paper were) unless
  ``filter_illogical=False``. Nothing is dropped silently: each reason is logged once on
  the ``vfm.observations`` logger with its count, and returned in ``LoadResult.removed``.
  A row that matches several reasons is counted under the first, in the order of
  ``FILTER_REASONS``.
* With ``keep_out_of_range=True`` (``vfm evaluate``, which runs the instrument-fault
  detectors over the rows), a row whose only problem is an input outside its physical span
  (:data:`vfm_core.sensor_faults.DEFAULT_RANGES`: a negative pressure, a choke or a fraction
  outside 0..1) is kept with its raw values and counted in ``LoadResult.kept`` under
  :data:`KEPT_OUT_OF_RANGE`: the detectors raise an ``out_of_range`` fault there, the study
  predicts the row with a stand-in for that input and learns nothing from it. A row is kept
  so when it passes every other check with those inputs set aside; a zero pressure lies
  inside the span (0..1500 bar a) and is still removed.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

import numpy as np
import pandas as pd

from vfm_core.errors import DataError, ObservationFormatError
from vfm_core.fileio import write_with
from vfm_core.schema import (
    INPUT_COLUMNS,
    OPTIONAL_RATE_COLUMNS,
    REQUIRED_COLUMNS,
    SOURCE,
    SOURCES,
    TARGET,
    TIME,
    UNITS,
    WELL,
)
from vfm_core.separator_format import (
    SEPARATOR_COLUMN,
    SEPARATOR_SOURCE,
    SeparatorData,
    split_separator_rows,
)

__all__ = [
    "LoadResult",
    "load_observations",
    "validate_frame",
    "save_observations",
    "outside_span",
]

logger = logging.getLogger("vfm.observations")

CSV_SUFFIXES: tuple[str, ...] = (".csv", ".csv.gz")
PARQUET_SUFFIXES: tuple[str, ...] = (".parquet", ".pq")

#: Why a row may be removed, in priority order (a row is counted under the first that fits).
FILTER_REASONS: tuple[str, ...] = (
    "non-finite input",
    "negative or zero pressure",
    "p_down >= p_up",
    "choke outside 0..1",
    "fraction outside 0..1",
    "fractions sum above 1",
    "negative rate",
    "rate without source",
    "source without rate",
    "duplicate row",
)

#: Why a row with an impossible input is kept (``keep_out_of_range``): see the module docstring.
KEPT_OUT_OF_RANGE = "input out of range"

#: Slack on eta_gas + eta_oil <= 1, so fractions computed in floating point are not removed.
FRACTION_SUM_TOLERANCE = 1e-9

# The cells pandas reads as missing by default (documented in ``pandas.read_csv``). In a
# numeric column they mean "empty"; well ids and sources are read literally, so a well
# called "NA" stays "NA".
_NA_TOKENS: tuple[str, ...] = (
    "",
    "#N/A",
    "#N/A N/A",
    "#NA",
    "-1.#IND",
    "-1.#QNAN",
    "-NaN",
    "-nan",
    "1.#IND",
    "1.#QNAN",
    "<NA>",
    "N/A",
    "NA",
    "NULL",
    "NaN",
    "None",
    "n/a",
    "nan",
    "null",
)

_TIME_EXAMPLE = "2019-03-01T06:00:00Z"
# The pandas nanosecond range; times outside it cannot be held as datetime64[ns].
_TIME_MIN = pd.Timestamp.min.tz_localize("UTC")
_TIME_MAX = pd.Timestamp.max.tz_localize("UTC")


@dataclass
class LoadResult:
    """A checked observation frame and what was done to it on the way in.

    ``frame`` is the typed, time-ordered frame (see the module docstring); ``path`` the
    file (or frame name) it came from; ``n_read`` the number of data rows in the input;
    ``removed`` the number of rows removed per reason (only reasons with a count above
    zero); ``reordered`` whether rows had to be sorted into (time, well) order; ``kept`` the
    rows kept although an input lies outside its physical span, per reason
    (:data:`KEPT_OUT_OF_RANGE`; only with ``keep_out_of_range``).
    """

    frame: pd.DataFrame
    path: str
    n_read: int
    removed: dict[str, int] = field(default_factory=dict)
    reordered: bool = False
    #: the separators' readings and member wells (empty without separator rows)
    separators: SeparatorData = field(default_factory=SeparatorData)
    kept: dict[str, int] = field(default_factory=dict)

    def summary(self) -> str:
        """One short sentence block for people, e.g. for a CLI or a log line."""
        kept = len(self.frame)
        text = f"{self.path}: {_rows(self.n_read)} read, {kept:,} kept"
        n_removed = sum(self.removed.values())
        if n_removed:
            reasons = ", ".join(f"{reason}: {count:,}" for reason, count in self.removed.items())
            text += f"; removed {n_removed:,} ({reasons})"
        for reason, count in self.kept.items():
            text += f"; {reason}: {_rows(count)} kept with raw values (out_of_range faults)"
        if self.separators:
            text += f"; {len(self.separators.readings):,} separator readings set apart"
        if self.reordered:
            text += "; rows were re-sorted into time order"
        return text + "."


def load_observations(
    path: str | os.PathLike[str],
    *,
    filter_illogical: bool = True,
    separators: dict[str, str] | None = None,
    keep_out_of_range: bool = False,
) -> LoadResult:
    """Read an observation file (``.csv``, ``.csv.gz``, ``.parquet`` or ``.pq``) and check it.

    Raises :class:`DataError` if the file does not exist and
    :class:`ObservationFormatError` if it breaks the format; see the module docstring for
    what is checked, what is removed and how rows are numbered in messages. ``separators``
    maps wells to separators, as for :func:`validate_frame`; ``keep_out_of_range`` keeps the
    rows whose only problem is an input outside its physical span (module docstring).
    """
    file = Path(path)
    name = str(path)
    kind = _format_of(file)
    if not file.exists():
        raise DataError(
            f"The observation file {name} does not exist. Check the path "
            f"(relative paths are taken from {Path.cwd()})."
        )
    if not file.is_file():
        raise DataError(f"{name} is not a file; give the path of an observation file.")
    raw = _read_csv(file, name) if kind == "csv" else _read_parquet(file, name)
    return validate_frame(
        raw,
        name=name,
        filter_illogical=filter_illogical,
        separators=separators,
        keep_out_of_range=keep_out_of_range,
    )


def validate_frame(
    frame: pd.DataFrame,
    *,
    name: str = "<frame>",
    filter_illogical: bool = True,
    separators: dict[str, str] | None = None,
    keep_out_of_range: bool = False,
) -> LoadResult:
    """Check, type, filter and sort an observation frame held in memory.

    Accepts text columns (as read from CSV) as well as typed ones. ``name`` stands for
    the file in messages. The input frame is not changed. ``separators`` maps wells to the
    separators they flow into (configuration; the ``separator`` column does the same).
    ``keep_out_of_range``: keep a row whose only problem is an input outside its physical
    span, counted in ``LoadResult.kept`` (module docstring).
    """
    missing = [column for column in REQUIRED_COLUMNS if column not in frame.columns]
    if missing:
        found = ", ".join(map(str, frame.columns)) or "none"
        raise ObservationFormatError(
            f"missing required column(s) {_quoted(missing)}. An observation file needs the "
            f"columns {', '.join(REQUIRED_COLUMNS)} (q_total and source may have empty "
            f"cells); found: {found}.",
            path=name,
        )

    out = frame.reset_index(drop=True)
    out[TIME] = _parse_time(out[TIME], name)
    out[WELL] = _parse_well(out[WELL], name)
    rate_columns = [TARGET, *(c for c in OPTIONAL_RATE_COLUMNS if c in out.columns)]
    for column in (*INPUT_COLUMNS, *rate_columns):
        out[column] = _parse_numeric(out[column], column, name)
    out[SOURCE] = _parse_source(out[SOURCE], name)

    removed: dict[str, int] = {}
    kept: dict[str, int] = {}
    out, separator_data = split_separator_rows(out, name=name, mapping=separators, removed=removed)
    if filter_illogical:
        outside = outside_span(out) if keep_out_of_range else None
        keep = _filter(out, rate_columns, name, removed, outside)
        if outside is not None and (count := int((outside.any(axis=1) & keep).sum())):
            kept[KEPT_OUT_OF_RANGE] = count
            logger.warning(
                "%s: kept %s with an input outside its physical span (raw values; "
                "out_of_range sensor faults, predicted with a stand-in, not learned).",
                name,
                _rows(count),
            )
        out = out.loc[keep]

    times = pd.DatetimeIndex(out[TIME]).asi8
    well_codes, _ = pd.factorize(out[WELL], sort=True)
    order = np.lexsort((well_codes, times))  # lexsort is stable: ties keep file order
    reordered = bool(np.any(order != np.arange(len(order))))
    out = out.iloc[order].reset_index(drop=True)
    return LoadResult(
        frame=out,
        path=name,
        n_read=len(frame),
        removed=removed,
        reordered=reordered,
        separators=separator_data,
        kept=kept,
    )


def save_observations(frame: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write ``frame`` as CSV or Parquet (by suffix), atomically, and return the path.

    The frame is checked like :func:`validate_frame` (hard errors raise; no rows are
    removed) and written sorted by (time, well). The data go to a temporary file in the
    same directory that replaces ``path`` only once complete, so an interrupted write
    never leaves a half-written file. Parent directories are created. In CSV, times are
    ISO 8601 UTC (``2019-03-01T06:00:00Z``, with a fraction only if some time has one)
    and empty values are empty cells.
    """
    file = Path(path)
    kind = _format_of(file)
    loaded = validate_frame(frame, name=str(path), filter_illogical=False)
    checked = loaded.frame
    if loaded.separators:  # the readings go back in, in (time, well) order
        checked = pd.concat([checked, loaded.separators.rows()], ignore_index=True)
        checked = checked.sort_values([TIME, WELL], kind="stable").reset_index(drop=True)

    def write(temp: Path) -> None:
        with temp.open("wb") as handle:
            if kind == "csv":
                _write_csv(checked, handle, gzip=file.name.lower().endswith(".gz"))
            else:
                checked.to_parquet(handle, index=False)

    return write_with(file, write)


# --- reading -------------------------------------------------------------------------


def _format_of(file: Path) -> Literal["csv", "parquet"]:
    lower = file.name.lower()
    if lower.endswith(CSV_SUFFIXES):
        return "csv"
    if lower.endswith(PARQUET_SUFFIXES):
        return "parquet"
    raise ObservationFormatError(
        f"unknown file type; observation files end in one of "
        f"{', '.join(CSV_SUFFIXES + PARQUET_SUFFIXES)}. Rename or convert the file.",
        path=str(file),
    )


def _read_csv(file: Path, name: str) -> pd.DataFrame:
    try:
        header = pd.read_csv(file, nrows=0).columns
        known = set(REQUIRED_COLUMNS) | set(OPTIONAL_RATE_COLUMNS) | {SEPARATOR_COLUMN}
        # Format columns are read as literal text and parsed in validate_frame, which can
        # then name the offending cell; extra columns get the usual pandas inference.
        return pd.read_csv(
            file,
            dtype={column: str for column in header if column in known},
            keep_default_na=False,
            na_values={column: list(_NA_TOKENS) for column in header if column not in known},
        )
    except pd.errors.EmptyDataError:
        raise ObservationFormatError(
            f"the file is empty; it needs a header line with the columns "
            f"{', '.join(REQUIRED_COLUMNS)}.",
            path=name,
        ) from None
    except (pd.errors.ParserError, UnicodeDecodeError, EOFError, OSError) as exc:
        raise ObservationFormatError(
            f"the file cannot be read as CSV ({exc}). Check that it is a comma-separated "
            f"UTF-8 text file with the same number of cells in every row.",
            path=name,
        ) from exc


def _read_parquet(file: Path, name: str) -> pd.DataFrame:
    try:
        return pd.read_parquet(file)
    except (ValueError, OSError) as exc:  # pyarrow's ArrowInvalid is a ValueError
        raise ObservationFormatError(
            f"the file cannot be read as Parquet ({exc}). Check that it is a Parquet file, "
            f"or give it a .csv suffix if it is CSV.",
            path=name,
        ) from exc


# --- parsing one column --------------------------------------------------------------


def _parse_time(raw: pd.Series, name: str) -> pd.Series:
    if isinstance(raw.dtype, pd.DatetimeTZDtype):
        times = raw.dt.tz_convert("UTC")
    elif pd.api.types.is_datetime64_dtype(raw.dtype):
        times = raw.dt.tz_localize("UTC")  # naive times are taken as UTC
    else:
        # utc=True converts times with an offset and takes naive ones as UTC.
        times = pd.to_datetime(raw, format="ISO8601", utc=True, errors="coerce")
    bad = times.isna().to_numpy()
    if bad.any():
        position, others = _first_and_others(bad)
        value = raw.iloc[position]
        problem = (
            "the time is empty"
            if pd.isna(value) or not str(value).strip()
            else f"'{value}' is not an ISO 8601 time"
        )
        raise ObservationFormatError(
            f"{problem}{_others(others, 'an empty or unreadable time')}. Write times as "
            f"ISO 8601, e.g. {_TIME_EXAMPLE} (times without an offset are taken as UTC).",
            path=name,
            row=_row(position),
            column=TIME,
        )
    outside = ((times < _TIME_MIN) | (times > _TIME_MAX)).to_numpy()
    if outside.any():
        position, others = _first_and_others(outside)
        raise ObservationFormatError(
            f"'{raw.iloc[position]}' lies outside the supported years 1677..2262"
            f"{_others(others, 'such a time')}. Check the date.",
            path=name,
            row=_row(position),
            column=TIME,
        )
    return times.dt.as_unit("ns")


def _parse_well(raw: pd.Series, name: str) -> pd.Series:
    wells = _as_text(raw)
    empty = (wells == "").to_numpy()
    if empty.any():
        position, others = _first_and_others(empty)
        raise ObservationFormatError(
            f"the well id is empty{_others(others, 'an empty well id')}. Every row needs "
            f"the id of the well it was measured on.",
            path=name,
            row=_row(position),
            column=WELL,
        )
    return wells


def _parse_source(raw: pd.Series, name: str) -> pd.Series:
    sources = _as_text(raw)
    invalid = (~sources.isin(("", *SOURCES, SEPARATOR_SOURCE))).to_numpy()
    if invalid.any():
        position, others = _first_and_others(invalid)
        raise ObservationFormatError(
            f"'{sources.iloc[position]}' is not a valid source"
            f"{_others(others, 'an invalid source')}. Use "
            f"{_quoted((*SOURCES, SEPARATOR_SOURCE), ' or ')}, "
            f"or leave the cell empty where there is no measured rate.",
            path=name,
            row=_row(position),
            column=SOURCE,
        )
    return sources


def _parse_numeric(raw: pd.Series, column: str, name: str) -> pd.Series:
    if pd.api.types.is_numeric_dtype(raw.dtype) and not pd.api.types.is_bool_dtype(raw.dtype):
        return pd.Series(raw.to_numpy(dtype=np.float64, na_value=np.nan), name=column)
    values = pd.to_numeric(raw, errors="coerce")
    failed = values.isna().to_numpy() & raw.notna().to_numpy()
    if failed.any():
        # Only cells that failed are looked at as text: NA tokens there just mean "empty".
        failed_text = raw[failed].astype(str).str.strip()
        text = np.zeros(len(raw), dtype=bool)
        text[np.flatnonzero(failed)] = ~failed_text.isin(_NA_TOKENS).to_numpy()
        if text.any():
            position, others = _first_and_others(text)
            raise ObservationFormatError(
                f"'{raw.iloc[position]}' is not a number ({UNITS[column]})"
                f"{_others(others, 'text in this column')}. Write a number with a decimal "
                f"point, or leave the cell empty where there is no value.",
                path=name,
                row=_row(position),
                column=column,
            )
    return pd.Series(values.to_numpy(dtype=np.float64, na_value=np.nan), name=column)


def _as_text(raw: pd.Series) -> pd.Series:
    """Strings with surrounding whitespace removed; missing values become ""."""
    return raw.where(raw.notna(), "").astype(str).str.strip()


# --- filtering -----------------------------------------------------------------------


def outside_span(frame: pd.DataFrame) -> np.ndarray:
    """[rows, 6] True where an input is finite and outside its physical span
    (:data:`vfm_core.sensor_faults.DEFAULT_RANGES`, the order of ``INPUT_COLUMNS``)."""
    from vfm_core.sensor_faults import DEFAULT_RANGES

    x = frame[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64)
    low = np.array([DEFAULT_RANGES[c][0] for c in INPUT_COLUMNS])
    high = np.array([DEFAULT_RANGES[c][1] for c in INPUT_COLUMNS])
    with np.errstate(invalid="ignore"):
        return np.isfinite(x) & ((x < low) | (x > high))


def _filter(
    frame: pd.DataFrame,
    rate_columns: list[str],
    name: str,
    removed: dict[str, int],
    outside: np.ndarray | None = None,
) -> np.ndarray:
    """Return the mask of rows to keep; fill ``removed`` and log one warning per reason.
    ``outside`` [rows, 6]: inputs set aside (outside their span, kept for the detectors):
    the checks other than ``non-finite input`` do not see them."""
    columns = list(INPUT_COLUMNS)

    def col(column: str) -> np.ndarray:
        v = frame[column].to_numpy(dtype=np.float64)
        if outside is not None and column in columns:
            v = np.where(outside[:, columns.index(column)], np.nan, v)
        return v

    choke, p_up, p_down = col("choke"), col("p_up"), col("p_down")
    eta_gas, eta_oil, q_total = col("eta_gas"), col("eta_oil"), col(TARGET)
    inputs = frame[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64)
    rates = frame[rate_columns].to_numpy(dtype=np.float64)
    has_rate = ~np.isnan(q_total)
    has_source = (frame[SOURCE] != "").to_numpy()

    # NaN compares False, and rows with NaN inputs are taken by the first reason anyway (an
    # input set aside as outside its span is NaN here, so only the other checks see the row).
    masks = {
        "non-finite input": ~np.isfinite(inputs).all(axis=1),
        "negative or zero pressure": (p_up <= 0) | (p_down <= 0),
        "p_down >= p_up": p_down >= p_up,
        "choke outside 0..1": (choke < 0) | (choke > 1),
        "fraction outside 0..1": (eta_gas < 0) | (eta_gas > 1) | (eta_oil < 0) | (eta_oil > 1),
        "fractions sum above 1": eta_gas + eta_oil > 1 + FRACTION_SUM_TOLERANCE,
        # An infinite optional rate is as unusable as an infinite q_total.
        "negative rate": ((rates < 0) | np.isinf(rates)).any(axis=1),
        "rate without source": has_rate & ~has_source,
        "source without rate": has_source & ~has_rate,
    }
    drop = np.zeros(len(frame), dtype=bool)
    for reason in FILTER_REASONS:
        if reason == "duplicate row":
            # Only among rows still kept, so a good row is not lost to an earlier bad twin.
            mask = np.zeros(len(frame), dtype=bool)
            mask[~drop] = frame.loc[~drop, [WELL, TIME, SOURCE]].duplicated(keep="first")
        else:
            mask = masks[reason]
        hit = mask & ~drop
        count = int(hit.sum())
        if count:
            removed[reason] = count
            drop |= hit
            logger.warning(
                "%s: removed %s: %s (first at row %d).",
                name,
                _rows(count),
                reason,
                _row(int(np.flatnonzero(hit)[0])),
            )
    return ~drop


# --- writing -------------------------------------------------------------------------


def _write_csv(frame: pd.DataFrame, handle: IO[bytes], *, gzip: bool) -> None:
    text = frame.copy()
    text[TIME] = _iso_utc(frame[TIME])
    text.to_csv(
        handle,
        index=False,
        na_rep="",
        lineterminator="\n",
        encoding="utf-8",
        compression="gzip" if gzip else None,
    )


def _iso_utc(times: pd.Series) -> pd.Series:
    """UTC times as ISO 8601 text ending in Z; with nanoseconds only where some time has them."""
    whole = times.dt.strftime("%Y-%m-%dT%H:%M:%S")
    nanoseconds = pd.DatetimeIndex(times).asi8 % 1_000_000_000
    if not nanoseconds.any():
        return whole + "Z"
    fraction = pd.Series(nanoseconds, index=times.index).astype(str).str.zfill(9)
    return whole + "." + fraction + "Z"


# --- message helpers -----------------------------------------------------------------


def _row(position: int) -> int:
    """Data row ``position`` (0-based) as a message row number: header = 1, first row = 2."""
    return position + 2


def _first_and_others(mask: np.ndarray) -> tuple[int, int]:
    positions = np.flatnonzero(mask)
    return int(positions[0]), len(positions) - 1


def _others(count: int, what: str) -> str:
    if count == 0:
        return ""
    return f" ({count:,} other {'row has' if count == 1 else 'rows have'} {what} too)"


def _rows(count: int) -> str:
    return f"{count:,} row" if count == 1 else f"{count:,} rows"


def _quoted(names: tuple[str, ...] | list[str], separator: str = ", ") -> str:
    return separator.join(f"'{n}'" for n in names)
