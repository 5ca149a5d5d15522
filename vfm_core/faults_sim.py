"""Inject instrument faults into an observation frame, with the truth beside it.

For tests and benchmarks of :mod:`vfm_core.sensor_faults`: the frame's recorded inputs
change as a failing transmitter would record them; the true rates (``q_total`` and the
meters) do not, since the well itself does not change. Sizes are relative to the reading
(a fraction: ``0.05`` is 5 %), so one size means the same for every sensor's unit.

=================  ====================================================================
kind               what the recorded value becomes from ``start`` (for ``days``, or on)
=================  ====================================================================
``frozen``         the last reading before ``start``, repeated
``spike``          the first reading at or after ``start`` times ``1 + size`` (one sample)
``drift``          the reading times ``1 + size * (days since start) / 30`` (size per 30 days)
``offset``         the reading times ``1 + size``
``out_of_range``   ``-1`` (below every physical span)
=================  ====================================================================

A choke or a fraction is kept in 0..1 except for ``out_of_range``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from vfm_core.errors import ConfigError
from vfm_core.sensor_faults import KINDS, SENSORS
from vfm_core.timeutil import utc_timestamp

__all__ = ["inject_fault", "DEFAULT_SIZES"]

#: a default size per kind (relative to the reading; drift per 30 days)
DEFAULT_SIZES: dict[str, float] = {
    "frozen": 0.0,
    "spike": 0.10,
    "drift": 0.05,
    "offset": 0.05,
    "out_of_range": 0.0,
}


def inject_fault(
    frame: pd.DataFrame,
    well: str,
    sensor: str,
    kind: str,
    start: Any,
    *,
    size: float | None = None,
    days: float | None = None,
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """A copy of ``frame`` with one fault on ``sensor`` of ``well`` from ``start`` (a time
    the frame's ``time`` column compares with; ISO string or Timestamp, UTC) for ``days``
    days (None: to the end; a spike is one sample), and the truth: ``{well, sensor, kind,
    start, end, size, rows}`` (times ISO 8601 UTC; ``start`` is the first affected row)."""
    if sensor not in SENSORS:
        raise ConfigError(f"Unknown sensor {sensor!r}; valid: {list(SENSORS)}.")
    if kind not in KINDS:
        raise ConfigError(f"Unknown fault kind {kind!r}; valid: {list(KINDS)}.")
    size = DEFAULT_SIZES[kind] if size is None else float(size)
    out = frame.copy()
    times = pd.to_datetime(out["time"], utc=True)
    t0 = utc_timestamp(start)
    t1 = t0 + pd.Timedelta(days=days) if days is not None else None
    of_well = (out["well"] == well).to_numpy()
    after = of_well & (times >= t0).to_numpy()
    if t1 is not None:
        after &= (times < t1).to_numpy()
    rows = np.flatnonzero(after)
    if kind == "spike":
        rows = rows[:1]
    if not len(rows):
        raise ConfigError(f"{well} has no rows from {t0} on: nothing to inject.")
    col = out.columns.get_loc(sensor)
    values = out[sensor].to_numpy(dtype=float).copy()
    if kind == "frozen":
        before = np.flatnonzero(of_well & (times < t0).to_numpy())
        if not len(before):
            raise ConfigError(f"{well} has no reading before {t0} to freeze at.")
        values[rows] = values[before[-1]]
    elif kind in ("spike", "offset"):
        values[rows] = values[rows] * (1.0 + size)
    elif kind == "drift":
        elapsed = (times.iloc[rows] - t0).dt.total_seconds().to_numpy() / 86_400.0
        values[rows] = values[rows] * (1.0 + size * elapsed / 30.0)
    else:
        values[rows] = -1.0
    if sensor in ("choke", "eta_gas", "eta_oil") and kind != "out_of_range":
        values[rows] = np.clip(values[rows], 0.0, 1.0)
    out.iloc[:, col] = values
    t_rows = times.iloc[rows]
    truth = {
        "well": well,
        "sensor": sensor,
        "kind": kind,
        "start": t_rows.iloc[0].isoformat(),
        "end": None if (t1 is None and kind != "spike") else t_rows.iloc[-1].isoformat(),
        "size": size,
        "rows": int(len(rows)),
    }
    return out, truth
