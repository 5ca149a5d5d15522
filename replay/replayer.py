"""Replay an observation file through a running service, over Zenoh, exactly as live data arrive.

For each row in time order (from ``start`` on): the sensor sample on
``<prefix>/<well>/sensors``, then, if the row has one, the measurement on
``<prefix>/<well>/measurements/<source>``. Every publisher uses BLOCK congestion control
(with a long ``wait_before_close``), so a busy service slows the replay down instead of
losing messages, and nothing is sent before the service's subscriber has matched.
Predictions are collected from ``<prefix>/*/prediction`` and scored against the file's
measurements at the end, like ``vfm evaluate`` scores its prequential predictions.

This module talks to the service only over Zenoh; it never imports ``service``.
"""

from __future__ import annotations

import json
import math
import secrets
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

import numpy as np
import pandas as pd
import zenoh
from pydantic import ValidationError
from tqdm import tqdm

from vfm_core.errors import ConfigError, DataError, VFMError
from vfm_core.messages import (
    Measurement,
    SensorSample,
    measurement_key,
    sensors_key,
    validate_prefix,
)
from vfm_core.schema import INPUT_COLUMNS, SOURCE, SOURCES, TARGET, TIME, WELL
from vfm_core.jobs.study import mape

__all__ = ["ReplayResult", "replay_frame", "replay_config", "ReplayError"]

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


class ReplayError(VFMError):
    """The replay could not run (no service matched, the link closed)."""


def _ns(when: datetime) -> int:
    return ((when - _EPOCH) // timedelta(microseconds=1)) * 1000


@dataclass
class ReplayResult:
    """What a replay sent, received and scored (rates Sm3/h, MAPE in percent)."""

    start: pd.Timestamp | None
    rows: int
    samples_sent: int
    measurements_sent: int
    predictions_received: int
    missing: int
    elapsed_s: float
    #: one row per scored measurement: time, well, source, measured, predicted (NaN if none)
    scored: pd.DataFrame
    per_well: pd.DataFrame = field(default_factory=pd.DataFrame)
    overall_mape: float = float("nan")
    mean_mape: float = float("nan")
    skipped: int = 0

    def summary(self) -> str:
        rate = self.rows / self.elapsed_s if self.elapsed_s > 0 else float("nan")
        since = f" from {self.start.isoformat()}" if self.start is not None else ""
        lines = [
            f"Replayed {self.rows:,} rows{since} ({self.samples_sent:,} sensor samples, "
            f"{self.measurements_sent:,} measurements) in {self.elapsed_s:.1f} s ({rate:,.0f} rows/s).",
            f"Predictions: {self.predictions_received:,} received; {self.missing:,} sample(s) got none "
            "(a well without a model yet gets no prediction until its first measurement; the rest were lost).",
        ]
        if self.skipped:
            lines.append(
                f"{self.skipped:,} row(s) were not sent: their values fail the message schema."
            )
        if not self.per_well.empty:
            lines.append("MAPE of the received predictions against the file's measurements:")
            lines.append(f"  {'well':<10} {'MAPE %':>8} {'n':>7}")
            for r in self.per_well.itertuples():
                lines.append(f"  {r.well:<10} {r.mape:>8.2f} {r.n:>7,}")
            n_all = int(self.per_well["n"].sum())
            lines.append(
                f"  {'all':<10} {self.overall_mape:>8.2f} {n_all:>7,}   "
                f"(pooled; mean over wells {self.mean_mape:.2f})"
            )
        else:
            lines.append("No measurement after the start could be scored.")
        return "\n".join(lines)


def replay_config(
    connect: Sequence[str], *, mode: str = "peer", block_wait_before_close_ms: int = 600_000
) -> zenoh.Config:
    """A loopback-safe Zenoh config for the replay: connect only, no multicast, no listener."""
    if mode not in ("peer", "client"):
        raise ConfigError(f"Zenoh mode '{mode}' is not valid for replay; choose peer or client.")
    if not connect:
        raise ConfigError("Give at least one --connect endpoint, e.g. tcp/127.0.0.1:7447.")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5(
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        json.dumps(block_wait_before_close_ms * 1000),  # microseconds
    )
    return cfg


class _Collector:
    """Predictions from ``<prefix>/*/prediction`` on a FifoChannel, read by one thread."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.predictions: dict[tuple[str, int], float] = {}
        self.count = 0
        self.last_at = time.monotonic()
        self.bad = 0
        self._lock = threading.Lock()
        self._session = session
        self._token = secrets.token_bytes(16)
        self._stop_key = f"{prefix}/_vfm-replay-control/prediction"
        self._sub = session.declare_subscriber(
            f"{prefix}/*/prediction", zenoh.handlers.FifoChannel(65536)
        )
        n_prefix = len(prefix) + 1
        self._thread = threading.Thread(
            target=self._run, args=(n_prefix,), name="vfm-replay-rx", daemon=True
        )
        self._thread.start()

    def _run(self, n_prefix: int) -> None:
        for sample in self._sub:
            key = str(sample.key_expr)
            if key == self._stop_key:
                att = sample.attachment
                if att is not None and secrets.compare_digest(att.to_bytes(), self._token):
                    return
                continue
            well = key[n_prefix:].rsplit("/", 1)[0]
            try:
                data = json.loads(sample.payload.to_bytes())
                t = datetime.fromisoformat(str(data["time"]).replace("Z", "+00:00"))
                t = t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)
                q = float(data["q_total"])
            except (ValueError, KeyError, TypeError):
                self.bad += 1
                continue
            with self._lock:
                self.predictions[(well, _ns(t))] = q
                self.count += 1
                self.last_at = time.monotonic()

    def close(self) -> None:
        self._session.put(
            self._stop_key,
            b"",
            attachment=self._token,
            allowed_destination=zenoh.Locality.SESSION_LOCAL,
        )
        self._thread.join(5)
        self._sub.undeclare()


def _wait_matching(pub: zenoh.Publisher, key: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    # the stubs say bool, zenoh 1.10 returns a MatchingStatus (always truthy): read .matching
    while not getattr(pub.matching_status, "matching", False):
        if time.monotonic() > deadline:
            raise ReplayError(
                f"No service subscribes to {key} after {timeout:g} s. Start `vfm serve` first, and check "
                "that --connect points at its Zenoh endpoint (or the router) and --prefix matches."
            )
        time.sleep(0.01)


def replay_frame(
    frame: pd.DataFrame,
    *,
    connect: Sequence[str] = ("tcp/127.0.0.1:7447",),
    prefix: str = "vfm",
    start: str | pd.Timestamp | None = None,
    speed: float | None = None,
    mode: str = "peer",
    match_timeout: float = 30.0,
    idle_timeout: float = 3.0,
    final_timeout: float = 600.0,
    progress: bool = True,
    block_wait_before_close_ms: int = 600_000,
) -> ReplayResult:
    """Replay a loaded observation frame (time-sorted, see ``load_observations``) through a service.

    ``speed``: N times real time; None = as fast as the service takes it. At the end the
    replay waits until a prediction arrived for every sample, or until none arrived for
    ``idle_timeout`` seconds (wells without a model never answer), at most ``final_timeout``.
    """
    validate_prefix(prefix)
    if speed is not None and not (math.isfinite(speed) and speed > 0):
        raise ConfigError(f"--speed must be a positive number, not {speed}.")
    start_ts = None
    rows = frame
    if start is not None:
        try:
            start_ts = pd.Timestamp(start)
        except (ValueError, TypeError):
            raise ConfigError(
                f"--start '{start}' is not a date; write it like 2019-01-01."
            ) from None
        start_ts = (
            start_ts.tz_localize("UTC") if start_ts.tzinfo is None else start_ts.tz_convert("UTC")
        )
        rows = frame[frame[TIME] >= start_ts]
    if rows.empty:
        raise DataError(
            "No rows to replay"
            + (f" on or after {start_ts.date()}" if start_ts is not None else "")
            + "."
        )
    rows = rows.reset_index(drop=True)

    session = zenoh.open(
        replay_config(connect, mode=mode, block_wait_before_close_ms=block_wait_before_close_ms)
    )
    collector: _Collector | None = None
    publishers: dict[str, zenoh.Publisher] = {}
    sent_samples: list[tuple[str, int]] = []
    measurements_sent = 0
    skipped = 0
    started = time.monotonic()
    try:
        collector = _Collector(session, prefix)

        def publisher(key: str) -> zenoh.Publisher:
            pub = publishers.get(key)
            if pub is None:
                pub = session.declare_publisher(
                    key,
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                _wait_matching(pub, key, match_timeout)
                publishers[key] = pub
            return pub

        # match once before the clock starts, and let the service see our subscriber
        first_well = str(rows[WELL].iloc[0])
        publisher(sensors_key(prefix, first_well))
        time.sleep(0.3)

        times = pd.DatetimeIndex(rows[TIME])
        t0_data = times[0]
        started = time.monotonic()
        last_sent: dict[str, int] = {}
        wells = rows[WELL].astype(str).to_numpy()
        x = rows[list(INPUT_COLUMNS)].to_numpy(dtype=float)
        q = rows[TARGET].to_numpy(dtype=float)
        src = rows[SOURCE].astype(str).to_numpy()
        py_times = [t.to_pydatetime() for t in times]
        for i in tqdm(
            range(len(rows)),
            total=len(rows),
            unit="row",
            desc="replay",
            disable=not progress,
            mininterval=0.5,
        ):
            well = wells[i]
            when = py_times[i]
            if speed is not None:
                due = started + (times[i] - t0_data).total_seconds() / speed
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            t_ns = _ns(when)
            if (
                last_sent.get(well) != t_ns
            ):  # a second row at the same time carries only its measurement
                try:
                    payload = SensorSample(
                        time=when,
                        choke=x[i, 0],
                        p_up=x[i, 1],
                        p_down=x[i, 2],
                        t_up=x[i, 3],
                        eta_gas=x[i, 4],
                        eta_oil=x[i, 5],
                    ).model_dump_json()
                except ValidationError:
                    skipped += 1
                    continue
                publisher(sensors_key(prefix, well)).put(payload)
                sent_samples.append((well, t_ns))
                last_sent[well] = t_ns
            if src[i] in SOURCES and np.isfinite(q[i]):
                payload = Measurement(time=when, q_total=float(q[i])).model_dump_json()
                publisher(measurement_key(prefix, well, src[i])).put(payload)
                measurements_sent += 1

        # wait for the answers: all of them, or until they stop coming
        deadline = time.monotonic() + final_timeout
        expected = set(sent_samples)
        while time.monotonic() < deadline:
            with collector._lock:
                got = (
                    sum(1 for k in expected if k in collector.predictions)
                    if collector.count >= len(expected)
                    else -1
                )
                idle = time.monotonic() - collector.last_at
            if got == len(expected):
                break
            if idle > idle_timeout and time.monotonic() - started > idle_timeout:
                break
            time.sleep(0.05)
        elapsed = time.monotonic() - started
    finally:
        try:
            if collector is not None:
                collector.close()
            for pub in publishers.values():
                pub.undeclare()
        finally:
            session.close()

    predictions = dict(collector.predictions)
    missing = sum(1 for k in sent_samples if k not in predictions)
    return _score(
        rows,
        predictions,
        start_ts,
        sent=len(sent_samples),
        measurements=measurements_sent,
        received=collector.count,
        missing=missing,
        elapsed=elapsed,
        skipped=skipped,
    )


def _score(
    rows: pd.DataFrame,
    predictions: dict[tuple[str, int], float],
    start: pd.Timestamp | None,
    *,
    sent: int,
    measurements: int,
    received: int,
    missing: int,
    elapsed: float,
    skipped: int,
) -> ReplayResult:
    measured = rows[rows[SOURCE].isin(SOURCES) & rows[TARGET].notna()]
    t_ns = pd.DatetimeIndex(measured[TIME]).as_unit("ns").asi8
    keys = zip(measured[WELL].astype(str), (int(t) // 1000 * 1000 for t in t_ns), strict=True)
    predicted = np.array([predictions.get(k, np.nan) for k in keys], dtype=float)
    scored = pd.DataFrame(
        {
            "time": measured[TIME].to_numpy(),
            "well": measured[WELL].astype(str).to_numpy(),
            "source": measured[SOURCE].to_numpy(),
            "measured": measured[TARGET].to_numpy(dtype=float),
            "predicted": predicted,
        }
    )
    records = []
    for well, g in scored.groupby("well", sort=True):
        ok = np.isfinite(g["predicted"].to_numpy())
        records.append(
            {"well": well, "mape": mape(g["predicted"], g["measured"]), "n": int(ok.sum())}
        )
    per_well = pd.DataFrame(records, columns=["well", "mape", "n"])
    overall = mape(scored["predicted"], scored["measured"]) if len(scored) else float("nan")
    mean = float(per_well["mape"].mean()) if len(per_well) else float("nan")
    return ReplayResult(
        start,
        len(rows),
        sent,
        measurements,
        received,
        missing,
        elapsed,
        scored,
        per_well,
        overall,
        mean,
        skipped,
    )
