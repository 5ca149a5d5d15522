"""A service store's history in the observation format: for ``vfm diagnose --store``,
``vfm export`` and ``GET /wells/{well}/history.csv``.

The store is opened read-only (SQLite URI ``mode=ro``), so an export never disturbs a
running service (WAL lets it read while the service writes).

The rows (columns of README.md's observation format, units at the boundary: choke
fraction 0..1, pressures bar absolute, t_up degC, mass fractions 0..1, rates Sm3/h at
standard conditions, times UTC):

* one row per stored sensor sample: ``time, well, choke, p_up, p_down, t_up, eta_gas,
  eta_oil``, with ``q_total`` and ``source`` empty;
* a measurement the service learned from (MPFM reading or well test) fills ``q_total``
  and ``source`` of the row of the sample it was paired with when both have the same time
  (the usual case: a meter reading sent with its sample); otherwise it is a row of its
  own at the measurement's time carrying the paired sample's inputs (exactly what the
  service learned from); an MPFM reading and a well test at the same sample's time give
  that sample two rows, one per source, as the observation format has it;
* measurements still pending or never paired have no inputs and are left out (their
  count is in ``DataFrame.attrs["left_out"]``).

``DataFrame.attrs["models"]`` holds each well's model as its latest checkpoint has it:
``{well: {"model": "mm", "effects": ["erosion"], "method": "ol"}}`` (a well without a
checkpoint, or one from before effects were recorded, is not in it), so that
``vfm diagnose --store`` starts from the model the service runs.

Extra columns (the observation format keeps and ignores them): ``predicted`` (the
service's q_total at the sample, before learning from the measurement, Sm3/h; empty
while the well had no model), ``predicted_std``, ``predicted_p05``, ``predicted_p95``
(its interval, with a method that gives one) and ``version`` (of the model that
predicted).
"""

from __future__ import annotations

import csv
import io
import json
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pandas as pd

from vfm_core.errors import ConfigError
from vfm_core.timeutil import iso

__all__ = [
    "COLUMNS",
    "UNITS",
    "connect_read_only",
    "load_store",
    "iter_rows",
    "csv_lines",
    "export_store",
]

#: the columns of an export, in order: the observation format, then the service's own
COLUMNS: tuple[str, ...] = (
    "time",
    "well",
    "choke",
    "p_up",
    "p_down",
    "t_up",
    "eta_gas",
    "eta_oil",
    "q_total",
    "source",
    "predicted",
    "predicted_std",
    "predicted_p05",
    "predicted_p95",
    "version",
)

#: the units of the columns, as a CSV header comment says them
UNITS = (
    "time ISO 8601 UTC; choke fraction 0..1; p_up, p_down bar absolute; t_up degC; eta_gas, "
    "eta_oil mass fractions 0..1; q_total (measured), predicted, predicted_std, predicted_p05, "
    "predicted_p95 Sm3/h at standard conditions"
)

_INPUTS = "choke, p_up, p_down, t_up, eta_gas, eta_oil"

# samples (with a learned measurement at the same time, if any), then learned measurements
# whose time differs from their paired sample's, with the sample's inputs; time order
_ROWS_SQL = f"""
SELECT s.time_ns AS time_ns, s.well AS well, s.choke, s.p_up, s.p_down, s.t_up, s.eta_gas,
       s.eta_oil, m.q_total AS q_total, m.source AS source, s.q_total AS predicted,
       s.q_total_std AS predicted_std, s.q_total_p05 AS predicted_p05,
       s.q_total_p95 AS predicted_p95, s.version AS version
FROM samples s
LEFT JOIN measurements m
  ON m.well = s.well AND m.status = 'learned' AND m.time_ns = s.time_ns
     AND m.sample_time_ns = s.time_ns
WHERE {{where_s}}
UNION ALL
SELECT m.time_ns, m.well, {", ".join("m." + c.strip() for c in _INPUTS.split(","))},
       m.q_total, m.source, m.predicted, p.q_total_std, p.q_total_p05, p.q_total_p95, p.version
FROM measurements m
LEFT JOIN samples p ON p.well = m.well AND p.time_ns = m.sample_time_ns
WHERE m.status = 'learned' AND m.sample_time_ns IS NOT NULL AND m.time_ns != m.sample_time_ns
  AND {{where_m}}
ORDER BY time_ns, well, source
"""


def connect_read_only(path: str | Path) -> sqlite3.Connection:
    """A read-only connection to a service store (never writes, never takes the write lock)."""
    file = Path(path)
    if not file.is_file():
        raise ConfigError(
            f"The store {file} does not exist; give the path of a `vfm serve` store (store.path)."
        )
    uri = f"{file.resolve().as_uri()}?mode=ro"
    try:
        # check_same_thread off: a streamed HTTP answer reads its pages on pool threads
        con = sqlite3.connect(uri, uri=True, timeout=30.0, check_same_thread=False)
        con.execute("PRAGMA busy_timeout=30000")
        tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    except sqlite3.DatabaseError as exc:
        raise ConfigError(
            f"The store {file} cannot be read as an SQLite database ({exc}); give the path of "
            "a `vfm serve` store."
        ) from None
    if not {"samples", "measurements", "wells"} <= tables:
        con.close()
        raise ConfigError(f"{file} is an SQLite file but not a `vfm serve` store.")
    columns = {r[1] for r in con.execute("PRAGMA table_info(samples)")}
    if "q_total_std" not in columns:  # a schema-1 store not opened by a newer service yet
        con.close()
        raise ConfigError(
            f"The store {file} has the first schema version; start `vfm serve` on it once (it "
            "migrates the store in place), then export it."
        )
    return con


def _where(
    well: str | None, start_ns: int | None, end_ns: int | None
) -> tuple[str, str, list[Any]]:
    parts_s, parts_m, params_s, params_m = ["1"], ["1"], [], []
    for col, op, value in (
        ("well", "=", well),
        ("time_ns", ">=", start_ns),
        ("time_ns", "<", end_ns),
    ):
        if value is not None:
            parts_s.append(f"s.{col} {op} ?")
            parts_m.append(f"m.{col} {op} ?")
            params_s.append(value)
            params_m.append(value)
    return " AND ".join(parts_s), " AND ".join(parts_m), [*params_s, *params_m]


def iter_rows(
    con: sqlite3.Connection,
    well: str | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    *,
    page: int = 5000,
    limit: int | None = None,
) -> Iterator[tuple[Any, ...]]:
    """The export's rows (:data:`COLUMNS`, time as epoch ns) in time order, read a page at a
    time so that a large store is never held in memory."""
    sent = 0
    cursor_ns = start_ns
    while True:
        where_s, where_m, params = _where(well, cursor_ns, end_ns)
        sql = _ROWS_SQL.format(where_s=where_s, where_m=where_m) + " LIMIT ?"
        rows = con.execute(sql, [*params, page + 1]).fetchall()
        if len(rows) <= page:
            chunk, more = rows, False
        else:
            # stop before the last time of the page: the next page starts there, whole
            last = rows[page][0]
            chunk = [r for r in rows[:page] if r[0] < last]
            if not chunk:  # pragma: no cover - more than a page of rows at one time
                chunk = [r for r in rows if r[0] == last]
                last = last + 1
            more, cursor_ns = True, last
        for row in chunk:
            if limit is not None and sent >= limit:
                return
            sent += 1
            yield row
        if not more:
            return


def _left_out(con: sqlite3.Connection, well: str | None) -> int:
    sql = "SELECT COUNT(*) FROM measurements WHERE status != 'learned'"
    params: list[Any] = []
    if well is not None:
        sql += " AND well = ?"
        params.append(well)
    return int(con.execute(sql, params).fetchone()[0])


def stored_models(con: sqlite3.Connection, well: str | None = None) -> dict[str, dict[str, Any]]:
    """Each well's model as its latest checkpoint records it (``extra.spec``: the base
    model, its effects as the texts that rebuild them, the method); ``well``: that one only."""
    sql = (
        "SELECT c.well, c.extra FROM checkpoints c JOIN (SELECT well, MAX(id) AS id FROM"
        " checkpoints GROUP BY well) m ON c.id = m.id"
    )
    params: list[Any] = []
    if well is not None:
        sql += " WHERE c.well = ?"
        params.append(well)
    out: dict[str, dict[str, Any]] = {}
    try:
        rows = con.execute(sql, params).fetchall()
    except sqlite3.OperationalError:  # a store without checkpoints
        return out
    for name, extra in rows:
        try:
            spec = json.loads(extra).get("spec")
        except (ValueError, AttributeError):
            continue
        if (
            isinstance(spec, list)
            and len(spec) == 3
            and isinstance(spec[0], str)
            and isinstance(spec[1], list)
            and all(isinstance(e, str) for e in spec[1])
        ):
            out[str(name)] = {"model": spec[0], "effects": list(spec[1]), "method": str(spec[2])}
    return out


def load_store(path: str, well: str | None = None) -> pd.DataFrame:
    """A service store's history as an observation frame (see the module docstring); one
    well's with ``well``. The ``vfm.sources`` entry point ``store``."""
    con = connect_read_only(path)
    try:
        if well is not None:
            known = con.execute("SELECT 1 FROM wells WHERE well = ?", (well,)).fetchone()
            if known is None:
                wells = [r[0] for r in con.execute("SELECT well FROM wells ORDER BY well")]
                raise ConfigError(
                    f"The store {path} holds no well {well!r}; it holds "
                    f"{', '.join(wells[:20]) or 'none'}{' ...' if len(wells) > 20 else ''}."
                )
        frame = pd.DataFrame(list(iter_rows(con, well)), columns=list(COLUMNS))
        left_out = _left_out(con, well)
        models = stored_models(con, well)
    finally:
        con.close()
    frame["time"] = pd.to_datetime(frame["time"].astype("int64"), unit="ns", utc=True)
    for col in COLUMNS[2:9] + COLUMNS[10:14]:
        frame[col] = frame[col].astype("float64")
    frame["well"] = frame["well"].astype(str)
    frame["version"] = frame["version"].astype("Int64")
    frame.attrs["left_out"] = left_out
    frame.attrs["models"] = models
    frame.attrs["source"] = str(path)
    return frame


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    return str(value)


def csv_lines(
    con: sqlite3.Connection,
    well: str | None = None,
    start_ns: int | None = None,
    end_ns: int | None = None,
    *,
    limit: int | None = None,
    comment: bool = True,
    close: bool = False,
) -> Iterator[str]:
    """The export as CSV text, a few thousand lines per chunk: an optional ``#`` comment
    with the units, the header, then the rows (times ISO 8601 UTC)."""
    try:
        head = io.StringIO()
        if comment:
            head.write(f"# vfm store export{f' of {well}' if well else ''}; units: {UNITS}\n")
        csv.writer(head, lineterminator="\n").writerow(COLUMNS)
        yield head.getvalue()
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        n = 0
        for row in iter_rows(con, well, start_ns, end_ns, limit=limit):
            writer.writerow([iso(row[0]), *(_cell(v) for v in row[1:])])
            n += 1
            if n % 2000 == 0:
                yield buf.getvalue()
                buf.seek(0)
                buf.truncate()
        if buf.tell():
            yield buf.getvalue()
    finally:
        if close:
            con.close()


def export_store(path: str, out: str | Path, well: str | None = None) -> tuple[int, Path]:
    """Write a store's history (one well's with ``well``) to ``out`` (.parquet or .csv;
    a CSV without the comment line, so that every reader of the observation format takes
    it). Returns the rows written and the path."""
    from vfm_core.fileio import write_with

    target = Path(out)
    suffix = target.suffix.lower()
    if suffix not in (".parquet", ".csv"):
        raise ConfigError(f"The export goes to a .parquet or .csv file, not '{target.name}'.")
    frame = load_store(path, well)
    if suffix == ".csv":
        out_frame = frame.copy()
        out_frame["time"] = out_frame["time"].map(lambda t: t.isoformat().replace("+00:00", "Z"))
        write_with(target, lambda p: out_frame.to_csv(p, index=False))
    else:
        write_with(target, lambda p: frame.to_parquet(p, index=False))
    return len(frame), target
