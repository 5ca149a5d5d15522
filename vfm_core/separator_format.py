"""Separator rows in the observation format: what they are, what is refused, how they count.

A separator (or export meter) measures the total of the wells that flow into it. In an
observation file such a reading is one row with ``source`` = ``separator``, ``well`` = the
separator's name, ``time`` and ``q_total`` = the measured total (Sm3/h), and every input
column empty. Which wells flow into which separator comes from an optional ``separator``
column on the wells' rows (the separator's name), or from a mapping (well -> separator)
given in the configuration, or both (they must agree).

:func:`split_separator_rows` is called by :func:`vfm_core.observations.validate_frame`; it
takes the separator rows out of the frame (so every tool that reads wells sees wells only)
and returns them as :class:`SeparatorData`. Hard errors (:class:`ObservationFormatError`,
each a sentence naming the row): a separator row with an input value, without a total, with
a negative or infinite total; a separator that no well flows into; a separator's name that is
also a well's; a well that names two separators. Two readings of one separator at one time:
the later rows are removed and counted as ``duplicate separator reading``.

How a reading counts (:func:`member_samples`): a reading at time t measures the sum of its
wells' rates at t. Each member well contributes its prediction at its latest sample at or
before t, if that sample is at most :data:`SAMPLE_WINDOW` old; a well whose latest sample is
older, that has no sample yet, or whose choke is closed (0) at that sample counts as shut in
and contributes 0. With synchronised samples (``vfm simulate --separator``) every well
flowing at t has a sample at t.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from vfm_core.errors import ObservationFormatError
from vfm_core.schema import INPUT_COLUMNS, OPTIONAL_RATE_COLUMNS, SOURCE, TARGET, TIME, WELL

__all__ = [
    "SEPARATOR_SOURCE",
    "SEPARATOR_COLUMN",
    "SAMPLE_WINDOW",
    "SeparatorData",
    "split_separator_rows",
    "member_samples",
]

#: ``source`` of a separator's reading
SEPARATOR_SOURCE = "separator"
#: the optional column of a well row naming the separator the well flows into
SEPARATOR_COLUMN = "separator"
#: a well's sample older than this at a reading counts as "no sample" (the well is shut in)
SAMPLE_WINDOW = pd.Timedelta(hours=6)


@dataclass
class SeparatorData:
    """The separators of a frame: ``readings`` (``time``, ``separator``, ``q_total`` in
    Sm3/h, sorted by time then separator) and ``members`` (separator -> its wells, in order
    of first appearance). Empty for a frame without separator rows."""

    readings: pd.DataFrame = field(
        default_factory=lambda: pd.DataFrame(
            {
                TIME: pd.Series([], dtype="datetime64[ns, UTC]"),
                SEPARATOR_COLUMN: pd.Series([], dtype=str),
                TARGET: pd.Series([], dtype=np.float64),
            }
        )
    )
    members: dict[str, list[str]] = field(default_factory=dict)

    def __bool__(self) -> bool:
        return len(self.readings) > 0

    def rows(self) -> pd.DataFrame:
        """The readings as rows of the observation format (inputs empty), for writing."""
        out = pd.DataFrame(
            {
                TIME: self.readings[TIME].to_numpy(),
                WELL: self.readings[SEPARATOR_COLUMN].to_numpy(),
                TARGET: self.readings[TARGET].to_numpy(),
                SOURCE: SEPARATOR_SOURCE,
            }
        )
        for column in INPUT_COLUMNS:
            out[column] = np.nan
        out[TIME] = pd.to_datetime(out[TIME], utc=True)
        return out


def split_separator_rows(
    frame: pd.DataFrame,
    *,
    name: str,
    mapping: Mapping[str, str] | None = None,
    removed: dict[str, int] | None = None,
) -> tuple[pd.DataFrame, SeparatorData]:
    """The frame without its separator rows, and the separators' readings and members.

    ``frame`` has parsed ``time``, ``well``, numeric inputs and ``q_total``, ``source``
    (index 0..n-1: data row i is message row i + 2). ``mapping`` (well -> separator) comes
    from the configuration. ``removed`` receives the count of duplicate readings removed.
    """
    is_sep = (frame[SOURCE] == SEPARATOR_SOURCE).to_numpy()
    column = _separator_column(frame, is_sep, name)
    wells_frame = frame.loc[~is_sep]
    members = _members(wells_frame, column, mapping or {}, name)
    if not is_sep.any():
        if mapping is None and column is None:
            return frame, SeparatorData()
        return wells_frame.reset_index(drop=True), SeparatorData(members=members)

    positions = np.flatnonzero(is_sep)
    sep = frame.loc[is_sep]
    total = _check_rows(sep, positions, name)
    names = sep[WELL].astype(str).to_numpy()
    clash = np.isin(names, wells_frame[WELL].astype(str).unique())
    if clash.any():
        i = int(np.flatnonzero(clash)[0])
        _fail(
            name,
            positions[i],
            WELL,
            f"'{names[i]}' is the name of a well as well as of a separator; give the "
            f"separator a name of its own.",
        )
    known = set(members)
    unknown = ~np.isin(names, list(known))
    if unknown.any():
        i = int(np.flatnonzero(unknown)[0])
        _fail(
            name,
            positions[i],
            WELL,
            f"no well flows into the separator '{names[i]}'"
            f"{_others(int(unknown.sum()) - 1)}. Name it in the '{SEPARATOR_COLUMN}' column "
            f"of its wells' rows, or map its wells to it in the configuration"
            + (f" (known separators: {', '.join(sorted(known))})." if known else "."),
        )
    readings = pd.DataFrame(
        {TIME: sep[TIME].to_numpy(), SEPARATOR_COLUMN: names, TARGET: total}
    ).reset_index(drop=True)
    readings[TIME] = pd.to_datetime(readings[TIME], utc=True)
    duplicate = readings.duplicated([TIME, SEPARATOR_COLUMN], keep="first").to_numpy()
    if duplicate.any() and removed is not None:
        removed["duplicate separator reading"] = int(duplicate.sum())
    readings = readings.loc[~duplicate].sort_values([TIME, SEPARATOR_COLUMN], kind="stable")
    return wells_frame.reset_index(drop=True), SeparatorData(
        readings=readings.reset_index(drop=True), members=members
    )


def _check_rows(sep: pd.DataFrame, positions: np.ndarray, name: str) -> np.ndarray:
    """The separator rows' totals (Sm3/h), after refusing rows with inputs or phase rates
    and totals that are empty, negative or infinite (``positions``: their data rows)."""
    inputs = sep[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64)
    filled = ~np.isnan(inputs)
    if filled.any():
        i, j = np.argwhere(filled)[0]
        _fail(
            name,
            positions[i],
            INPUT_COLUMNS[j],
            f"a separator row carries the separator's total only, but this one has "
            f"{INPUT_COLUMNS[j]} = {inputs[i, j]:g}{_others(int(filled.any(axis=1).sum()) - 1)}. "
            f"Leave the input columns of a separator row empty (the inputs belong on its "
            f"wells' rows).",
        )
    rate_columns = [c for c in OPTIONAL_RATE_COLUMNS if c in sep.columns]
    if rate_columns and sep[rate_columns].notna().to_numpy().any():
        i = int(np.flatnonzero(sep[rate_columns].notna().to_numpy().any(axis=1))[0])
        _fail(
            name,
            positions[i],
            rate_columns[0],
            "a separator row gives the total (q_total) only; leave q_gas, q_oil and q_water "
            "empty on it.",
        )
    total = sep[TARGET].to_numpy(dtype=np.float64)
    bad = ~np.isfinite(total) | (total < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        what = "is empty" if np.isnan(total[i]) else f"is {total[i]:g}"
        _fail(
            name,
            positions[i],
            TARGET,
            f"the separator's total {what}{_others(int(bad.sum()) - 1)}. A separator row "
            f"needs the measured total in Sm3/h, a finite number of at least 0.",
        )
    return total


def _separator_column(frame: pd.DataFrame, is_sep: np.ndarray, name: str) -> pd.Series | None:
    """The wells' ``separator`` column as text ("" = none), or None without the column."""
    if SEPARATOR_COLUMN not in frame.columns:
        return None
    text = frame[SEPARATOR_COLUMN].where(frame[SEPARATOR_COLUMN].notna(), "").astype(str)
    return text.str.strip()


def _members(
    wells: pd.DataFrame, column: pd.Series | None, mapping: Mapping[str, str], name: str
) -> dict[str, list[str]]:
    """separator -> wells (order of first appearance; the configuration's wells after)."""
    own: dict[str, str] = {}
    if column is not None:
        named = column.loc[wells.index]
        pairs = pd.DataFrame({WELL: wells[WELL].astype(str), SEPARATOR_COLUMN: named})
        pairs = pairs[pairs[SEPARATOR_COLUMN] != ""]
        both = pairs.drop_duplicates()
        twice = both[WELL].duplicated(keep=False).to_numpy()
        if twice.any():
            well = both[WELL].to_numpy()[twice][0]
            seps = sorted(both.loc[both[WELL] == well, SEPARATOR_COLUMN])
            first = int(pairs.index[pairs[WELL] == well][0])
            _fail(
                name,
                first,
                SEPARATOR_COLUMN,
                f"the well '{well}' names the separators {', '.join(seps)}; a well flows "
                f"into one separator. Correct the '{SEPARATOR_COLUMN}' column.",
            )
        own = dict(zip(both[WELL], both[SEPARATOR_COLUMN], strict=True))
    for well, sep in mapping.items():
        if well in own and own[well] != sep:
            raise ObservationFormatError(
                f"the well '{well}' flows into '{own[well]}' by the '{SEPARATOR_COLUMN}' "
                f"column but into '{sep}' by the configuration; make them agree.",
                path=name,
            )
        own.setdefault(str(well), str(sep))
    members: dict[str, list[str]] = {}
    for well, sep in own.items():
        members.setdefault(sep, []).append(well)
    return members


def member_samples(
    wells_frame: pd.DataFrame,
    readings: pd.DataFrame,
    members: Mapping[str, list[str]],
    *,
    window: pd.Timedelta = SAMPLE_WINDOW,
) -> pd.DataFrame:
    """For every reading and member well, the frame row of the well's latest sample at or
    before the reading within ``window`` (-1: none, the well counts as shut in), and whether
    the well is shut in (no such sample, or its choke is 0 there).

    Returns a frame ``reading`` (index into ``readings``), ``separator``, ``well``, ``row``
    (index into ``wells_frame``, -1 for none), ``shut`` (bool)."""
    out = []
    times_all = pd.DatetimeIndex(wells_frame[TIME]).asi8
    wells_all = wells_frame[WELL].astype(str).to_numpy()
    choke = wells_frame["choke"].to_numpy(dtype=np.float64)
    read_t = pd.DatetimeIndex(readings[TIME]).asi8
    read_sep = readings[SEPARATOR_COLUMN].astype(str).to_numpy()
    window_ns = int(window.value)
    for sep, wells in members.items():
        at = np.flatnonzero(read_sep == sep)
        if len(at) == 0:
            continue
        for well in wells:
            rows = np.flatnonzero(wells_all == well)
            t = times_all[rows]
            k = np.searchsorted(t, read_t[at], side="right") - 1
            ok = k >= 0
            row = np.where(ok, rows[np.clip(k, 0, None)] if len(rows) else -1, -1)
            ok &= (
                read_t[at] - np.where(row >= 0, times_all[np.clip(row, 0, None)], 0)
            ) <= window_ns
            row = np.where(ok, row, -1)
            shut = ~ok | (np.where(ok, choke[np.clip(row, 0, None)], 0.0) <= 0.0)
            out.append(
                pd.DataFrame(
                    {"reading": at, SEPARATOR_COLUMN: sep, WELL: well, "row": row, "shut": shut}
                )
            )
    if not out:
        return pd.DataFrame(columns=["reading", SEPARATOR_COLUMN, WELL, "row", "shut"])
    return pd.concat(out, ignore_index=True).sort_values(["reading", WELL], kind="stable")


def _fail(name: str, position: int, column: str, message: str) -> None:
    raise ObservationFormatError(message, path=name, row=int(position) + 2, column=column)


def _others(count: int) -> str:
    if count <= 0:
        return ""
    return f" ({count:,} other {'row does' if count == 1 else 'rows do'} too)"
