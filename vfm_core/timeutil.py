"""Time conventions, in one place: every time inside the VFM is UTC.

Files and messages carry ISO 8601 times (a naive time is taken as UTC); tensors and the
service's store carry int64 epoch nanoseconds, which cover 1677-09-21 to 2262-04-11
(:data:`TIME_MIN`, :data:`TIME_MAX`).
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pandas as pd

__all__ = [
    "TIME_MIN",
    "TIME_MAX",
    "utc",
    "utc_timestamp",
    "to_ns",
    "from_ns",
    "iso",
]

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
#: the earliest and latest times an int64 count of nanoseconds since 1970 can hold
TIME_MIN: pd.Timestamp = pd.Timestamp.min.tz_localize("UTC")
TIME_MAX: pd.Timestamp = pd.Timestamp.max.tz_localize("UTC")


def utc(when: datetime) -> datetime:
    """An aware UTC datetime (a naive one is taken as UTC)."""
    return when.replace(tzinfo=UTC) if when.tzinfo is None else when.astimezone(UTC)


def utc_timestamp(when: datetime | pd.Timestamp | str | int) -> pd.Timestamp:
    """A pandas Timestamp in UTC (a naive time is taken as UTC; an int is epoch ns)."""
    ts = pd.Timestamp(when, tz="UTC") if isinstance(when, int) else pd.Timestamp(when)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def to_ns(when: datetime) -> int:
    """Epoch nanoseconds of a datetime (naive = UTC), exact integer arithmetic at microseconds."""
    return ((utc(when) - _EPOCH) // timedelta(microseconds=1)) * 1000


def from_ns(ns: int) -> datetime:
    """The aware UTC datetime of epoch nanoseconds (microsecond precision)."""
    return _EPOCH + timedelta(microseconds=int(ns) // 1000)


def iso(ns: int | None) -> str | None:
    """ISO 8601 with a trailing ``Z`` for epoch nanoseconds (None stays None)."""
    return None if ns is None else from_ns(ns).isoformat().replace("+00:00", "Z")
