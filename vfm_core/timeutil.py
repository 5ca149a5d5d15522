"""Time conventions, in one place: every time inside the VFM is UTC.

Files and messages carry ISO 8601 times (a naive time is taken as UTC); tensors and the
service's store carry int64 epoch nanoseconds, which cover 1677-09-21 to 2262-04-11
(:data:`TIME_MIN`, :data:`TIME_MAX`).

:func:`time_problem` is the one rule for a time that comes from outside (a message, an
HTTP body or query): it must lie within the representable span, a day inside those limits
(:data:`REPRESENTABLE_MIN`, :data:`REPRESENTABLE_MAX`), and, where the caller asks, not
before a plausible earliest time (:data:`PLAUSIBLE_MIN`, 1970-01-01, by default) nor
further ahead than a given bound.
"""

from __future__ import annotations

import functools
from datetime import UTC, datetime, timedelta

import numpy as np
import pandas as pd

__all__ = [
    "TIME_MIN",
    "TIME_MAX",
    "REPRESENTABLE_MIN",
    "REPRESENTABLE_MAX",
    "PLAUSIBLE_MIN",
    "time_problem",
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
#: the span a time from outside may take: a day inside TIME_MIN..TIME_MAX, so that a
#: time zone offset or a few hours of arithmetic never leave the int64-nanosecond range
REPRESENTABLE_MIN = datetime(1677, 9, 22, tzinfo=UTC)
REPRESENTABLE_MAX = datetime(2262, 4, 10, tzinfo=UTC)
#: the default earliest plausible time of a measurement or sample (no MPFM before it)
PLAUSIBLE_MIN = datetime(1970, 1, 1, tzinfo=UTC)


def utc(when: datetime) -> datetime:
    """An aware UTC datetime (a naive one is taken as UTC)."""
    tz = when.tzinfo
    if tz is UTC:  # already: asked several times per sample, astimezone is the cost
        return when
    return when.replace(tzinfo=UTC) if tz is None else when.astimezone(UTC)


def time_problem(
    when: datetime,
    *,
    earliest: datetime | None = None,
    latest: datetime | None = None,
    what: str = "time",
) -> str | None:
    """Why ``when`` cannot be taken, as a sentence; None when it can.

    Always checked: the representable span (:data:`REPRESENTABLE_MIN` ..
    :data:`REPRESENTABLE_MAX`). ``earliest`` (e.g. :data:`PLAUSIBLE_MIN`) and ``latest``
    (e.g. now plus a clock-skew allowance) narrow it. A naive time is taken as UTC.
    """
    try:
        t = utc(when)
    except OverflowError:  # an offset pushes it past year 1 or 9999
        return (
            f"The {what} {when.isoformat()} lies outside the span the VFM can represent "
            f"({REPRESENTABLE_MIN.date()} to {REPRESENTABLE_MAX.date()})."
        )
    if t < REPRESENTABLE_MIN or t > REPRESENTABLE_MAX:
        return (
            f"The {what} {t.isoformat()} lies outside the span the VFM can represent "
            f"({REPRESENTABLE_MIN.date()} to {REPRESENTABLE_MAX.date()})."
        )
    if earliest is not None and t < utc(earliest):
        return (
            f"The {what} {t.isoformat()} lies before {utc(earliest).isoformat()}, the earliest "
            "plausible time; check the sender's clock and time zone."
        )
    if latest is not None and t > utc(latest):
        return f"The {what} {t.isoformat()} lies after {utc(latest).isoformat()}."
    return None


def utc_timestamp(when: datetime | pd.Timestamp | str | int) -> pd.Timestamp:
    """A pandas Timestamp in UTC (a naive time is taken as UTC; an int is epoch ns)."""
    ts = pd.Timestamp(when, tz="UTC") if isinstance(when, int) else pd.Timestamp(when)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def to_ns(when: datetime) -> int:
    """Epoch nanoseconds of a datetime (naive = UTC), exact integer arithmetic at microseconds."""
    d = utc(when) - _EPOCH  # exact: days, seconds and microseconds as integers
    return ((d.days * 86_400 + d.seconds) * 1_000_000 + d.microseconds) * 1000


def from_ns(ns: int) -> datetime:
    """The aware UTC datetime of epoch nanoseconds (microsecond precision)."""
    return _EPOCH + timedelta(microseconds=int(ns) // 1000)


def iso_many(ns: np.ndarray) -> list[str]:
    """:func:`iso` of many epoch nanoseconds at once (whole microseconds, as a datetime
    holds): seconds alone when the fraction is zero, else six digits, and a ``Z``."""
    us = np.asarray(ns, dtype=np.int64) // 1000
    stamps = us.astype("datetime64[us]")
    whole = np.datetime_as_string(stamps, unit="s")
    if (us % 1_000_000 == 0).all():
        return [s + "Z" for s in whole.tolist()]
    fine = np.datetime_as_string(stamps, unit="us")
    return [
        (w if u % 1_000_000 == 0 else f) + "Z"
        for w, f, u in zip(whole.tolist(), fine.tolist(), us.tolist(), strict=True)
    ]


def iso(ns: int | None) -> str | None:
    """ISO 8601 with a trailing ``Z`` for epoch nanoseconds (None stays None)."""
    return None if ns is None else _iso(ns)


@functools.lru_cache(maxsize=4096)  # every prediction's time: wells often share a second
def _iso(ns: int) -> str:
    return from_ns(ns).isoformat().replace("+00:00", "Z")
