"""Replay an observation file through a running service, exactly as live data arrive.

For each row in time order (from ``start`` on): the sensor sample on
``<prefix>/<well>/sensors`` (an input outside its physical span sent raw: the service
decides, see :meth:`replay.client.FieldClient.stream`), then, if the row has one, the measurement on
``<prefix>/<well>/measurements/<source>``, sent by the field client
(:class:`replay.client.FieldClient`) over Zenoh (or any :class:`replay.client.FieldBus`,
such as the service's in-memory transport). Every Zenoh publisher uses BLOCK congestion
control (with a long ``wait_before_close``), so a busy service slows the replay down
instead of losing messages, and nothing is sent before the service's subscriber has
matched. Predictions are collected from ``<prefix>/*/prediction`` and scored against the
file's measurements at the end, like ``vfm evaluate`` scores its prequential predictions.

This module talks to the service only through a bus; it never imports ``service``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from replay.client import FieldBus, FieldClient, ReplayError, Streamed, ZenohBus
from replay.delivery import DRAIN_S, Delivery, await_delivery, start_count
from vfm_core.errors import ConfigError, DataError
from vfm_core.jobs.study import mape
from vfm_core.messages import validate_prefix
from vfm_core.schema import SOURCE, SOURCES, TARGET, TIME, WELL
from vfm_core.timeutil import iso, utc_timestamp

__all__ = ["ReplayResult", "replay_frame", "ReplayError"]

#: samples without a prediction named in the summary (the rest are counted)
MISSING_SHOWN = 3


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
    #: the first few samples that got no prediction: (well, sample time ns)
    missing_samples: list[tuple[str, int]] = field(default_factory=list)
    #: samples sent with an input outside its physical span, raw (out_of_range faults)
    out_of_span: int = 0
    #: how long the replay waited at the end for the next answer (s)
    idle_timeout_s: float = 3.0
    #: separator readings sent
    readings_sent: int = 0
    #: one row per separator reading sent: separator, time, q_total (Sm3/h, as sent), and
    #: from the service's allocation, where it came: predicted (the sum of the wells'
    #: predictions), residual (Sm3/h), status ("learned", "allocated", "unused"; "" for none)
    readings: pd.DataFrame = field(default_factory=pd.DataFrame)
    #: what the service confirmed of the messages sent (None: it answers no flushes)
    delivery: Delivery | None = None

    def reading_lines(self) -> list[str]:
        """The separator readings in a sentence per separator: how many the service settled
        (allocated), how, and how close the sum of the wells' predictions came."""
        if not self.readings_sent:
            return []
        lines = []
        for sep, g in self.readings.groupby("separator", sort=True):
            settled = g[g["status"] != ""]
            if settled.empty:
                lines.append(
                    f"Separator {sep}: {len(g):,} reading(s) sent, none allocated: is '{sep}' in "
                    "the service's separators.members? (a reading of an unknown separator is "
                    "refused, its reason counted in /metrics)"
                )
                continue
            counts = settled["status"].value_counts()
            how = ", ".join(f"{k} {int(v):,}" for k, v in counts.items())
            used = settled[settled["status"] != "unused"]
            close = ""
            if len(used):
                rel = float((used["residual"].abs() / used["q_total"]).mean() * 100.0)
                close = f"; the wells' predictions summed to within {rel:.2f} % of the totals on average"
            waiting = len(g) - len(settled)
            lines.append(
                f"Separator {sep}: {len(g):,} reading(s) sent, {len(settled):,} allocated ({how})"
                + (
                    f", {waiting:,} not settled yet (waiting for their wells' samples)"
                    if waiting
                    else ""
                )
                + close
                + "."
            )
        return lines

    def _why_none(self) -> str:
        """Why samples get no prediction, as far as this replay can tell."""
        rules = (
            "a well without a model yet gets none until its first measurement, a sample the "
            "service rejects gets none, its reason counted in /metrics"
        )
        if self.delivery is not None and self.delivery.done:
            return f"(the service had handled every message: {rules})."
        if self.delivery is not None and self.delivery.gone:
            return f"({rules}; any other was not answered before the service went away)."
        return (
            f"({rules}; any other was not answered within --idle-timeout "
            f"({self.idle_timeout_s:g} s) of the answer before, when the replay stopped "
            "waiting: a busy service (a retrain, a loaded machine) answers later, into its "
            "store (vfm export), and a longer --idle-timeout waits for it)."
        )

    def summary(self) -> str:
        rate = self.rows / self.elapsed_s if self.elapsed_s > 0 else float("nan")
        since = f" from {self.start.isoformat()}" if self.start is not None else ""
        lines = [
            f"Replayed {self.rows:,} rows{since} ({self.samples_sent:,} sensor samples, "
            f"{self.measurements_sent:,} measurements"
            + (f", {self.readings_sent:,} separator readings" if self.readings_sent else "")
            + f") in {self.elapsed_s:.1f} s ({rate:,.0f} rows/s).",
            f"Predictions: {self.predictions_received:,} received; {self.missing:,} sample(s) got none "
            + self._why_none(),
        ]
        if self.delivery is not None:
            lines.append(self.delivery.line())
        elif self.missing > 0:
            sent = self.samples_sent + self.measurements_sent + self.readings_sent
            lines.append(
                f"The service's GET /health 'received' should reach the {sent:,} messages sent "
                "(plus any other senders'); if it stays below, messages were lost on the way "
                "(this service does not confirm what it took in: docs/guide/export-replay.md)."
            )
        if self.missing_samples:
            shown = ", ".join(f"{w} at {iso(t)}" for w, t in self.missing_samples)
            more = self.missing - len(self.missing_samples)
            lines.append(
                f"Without a prediction: {shown}" + (f" and {more:,} more." if more > 0 else ".")
            )
        if self.out_of_span:
            lines.append(
                f"{self.out_of_span:,} sample(s) with an input outside its physical span were sent "
                "with their raw values: a service that watches instrument faults raises an "
                "out_of_range fault on them, stands in for the input and holds their "
                "measurements; one that does not refuses them, its reason counted in /metrics."
            )
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
        lines += self.reading_lines()
        return "\n".join(lines)


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
    bus: FieldBus | None = None,
    readings: pd.DataFrame | None = None,
) -> ReplayResult:
    """Replay a loaded observation frame (time-sorted, see ``load_observations``) through a service.

    ``speed``: N times real time; None = as fast as the service takes it. At the end the
    replay waits until a prediction arrived for every sample, or until none arrived for
    ``idle_timeout`` seconds (wells without a model never answer; before the first answer,
    30 s: a service busy with its first samples answers late), at most ``final_timeout``.
    ``bus``: send over this bus (e.g. a service's in-memory transport) instead of opening
    a Zenoh session to ``connect`` (which is then not used); the caller keeps it open.
    ``readings``: separator readings (``LoadResult.separators.readings``), sent in time
    order among the rows (from ``start`` on); their allocations are collected and the
    sums' agreement with the totals reported.
    """
    validate_prefix(prefix)
    if speed is not None and not (math.isfinite(speed) and speed > 0):
        raise ConfigError(f"--speed must be a positive number, not {speed}.")
    rows, start_ts = _rows_from(frame, start)
    chosen = _readings_from(readings, start_ts)
    opened: ZenohBus | None = None
    if bus is None:
        bus = opened = ZenohBus.connect(
            connect,
            mode=mode,
            block_wait_before_close_ms=block_wait_before_close_ms,
            match_timeout=match_timeout,
        )
    try:
        with FieldClient(bus, prefix, match_timeout=match_timeout) as client:
            # match once before the clock starts, and let the service see our subscriber
            client.wait_for_service(str(rows[WELL].iloc[0]))
            # the service's count of messages taken in, to compare with what is sent
            start_at = start_count(client, match_timeout)
            if len(chosen):
                client.collect_allocations()
            sent = client.stream(rows, speed=speed, progress=progress, readings=chosen)
            delivery = _await_answers(
                client,
                sent,
                start_at,
                idle_timeout=idle_timeout,
                final_timeout=final_timeout,
                progress=progress,
            )
            elapsed = time.monotonic() - sent.started
    finally:
        if opened is not None:
            opened.close()

    result = _result(client, rows, start_ts, sent, elapsed, chosen)
    result.idle_timeout_s = idle_timeout
    result.delivery = delivery
    return result


def _result(
    client: FieldClient,
    rows: pd.DataFrame,
    start_ts: pd.Timestamp | None,
    sent: Streamed,
    elapsed: float,
    chosen: pd.DataFrame,
) -> ReplayResult:
    """The replay scored: what was sent against what came back."""
    predictions = dict(client.predictions)
    lacking = [k for k in sent.samples if k not in predictions]
    result = _score(
        rows,
        predictions,
        start_ts,
        sent=len(sent.samples),
        measurements=sent.measurements,
        received=client.count,
        missing=len(lacking),
        elapsed=elapsed,
        skipped=sent.skipped,
    )
    result.missing_samples = lacking[:MISSING_SHOWN]
    result.out_of_span = sent.out_of_span
    result.readings_sent = len(sent.readings)
    result.readings = _settled(chosen, sent.readings, dict(client.allocations))
    return result


def _await_answers(
    client: FieldClient,
    sent: Streamed,
    start_at: int | None,
    *,
    idle_timeout: float,
    final_timeout: float,
    progress: bool = False,
) -> Delivery | None:
    """After the last message: the service's word that it took in (and handled) them all
    (:mod:`replay.delivery`), or, from a service that answers no flushes (``start_at``
    None), the answers until they stop coming; then the separators' allocations."""
    if start_at is None:
        client.wait_for_answers(
            sent.samples,
            idle_timeout=idle_timeout,
            final_timeout=final_timeout,
            since=sent.started,
        )
        _wait_for_allocations(client, sent.readings, idle_timeout, final_timeout)
        return None
    delivery = await_delivery(
        client,
        set(sent.samples),
        sent=len(sent.samples) + sent.measurements + len(sent.readings),
        start=start_at,
        idle_timeout=idle_timeout,
        final_timeout=final_timeout,
        progress=progress,
    )
    # allocations published before the service's last word: only the replay's reader to wait for
    settle = DRAIN_S if delivery.done else idle_timeout
    _wait_for_allocations(client, sent.readings, settle, final_timeout)
    return delivery


def _readings_from(readings: pd.DataFrame | None, start: pd.Timestamp | None) -> pd.DataFrame:
    """The separator readings to send: those from ``start`` on (all without it)."""
    if readings is None:
        return pd.DataFrame(columns=[TIME, "separator", TARGET])
    return readings[readings[TIME] >= start] if start is not None else readings


def _wait_for_allocations(
    client: FieldClient, sent: list[tuple[str, int]], idle_timeout: float, final_timeout: float
) -> None:
    """Wait until every reading sent is allocated, or none came for ``idle_timeout`` s (the
    last reading waits for its wells' next samples, which may never come), at most
    ``final_timeout`` s."""
    if not sent:
        return
    wanted = set(sent)
    began = time.monotonic()
    seen, last = -1, began
    while time.monotonic() - began < final_timeout:
        got = sum(1 for k in wanted if k in client.allocations)
        if got == len(wanted):
            return
        if got != seen:
            seen, last = got, time.monotonic()
        elif time.monotonic() - last > idle_timeout:
            return
        time.sleep(0.05)


def _settled(
    readings: pd.DataFrame,
    sent: list[tuple[str, int]],
    allocations: dict[tuple[str, int], dict[str, object]],
) -> pd.DataFrame:
    """One row per reading sent (see :attr:`ReplayResult.readings`)."""
    columns = ["separator", "time", "q_total", "predicted", "residual", "status"]
    if not sent:
        return pd.DataFrame(columns=columns)
    stamps = pd.DatetimeIndex(readings[TIME]).as_unit("ns").asi8
    total = {
        (str(sep), int(t)): float(q)
        for sep, t, q in zip(readings["separator"], stamps, readings[TARGET], strict=True)
    }
    rows = []
    for sep, t in sent:
        a = allocations.get((sep, t), {})
        rows.append(
            {
                "separator": sep,
                "time": pd.Timestamp(t, tz="UTC"),
                "q_total": total.get((sep, t), float("nan")),
                "predicted": _number(a.get("predicted")),
                "residual": _number(a.get("residual")),
                "status": str(a.get("status", "")),
            }
        )
    return pd.DataFrame(rows, columns=columns)


def _number(value: object) -> float:
    """A number from a message field (NaN for none)."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")


def _rows_from(
    frame: pd.DataFrame, start: str | pd.Timestamp | None
) -> tuple[pd.DataFrame, pd.Timestamp | None]:
    """The rows to replay (those on or after ``start``, all without it), indexed from 0,
    and ``start`` as a UTC time; a sentence for a start that is no date or leaves no row."""
    start_ts = None
    rows = frame
    if start is not None:
        try:
            start_ts = utc_timestamp(start)
        except (ValueError, TypeError):
            raise ConfigError(
                f"--start '{start}' is not a date; write it like 2019-01-01."
            ) from None
        rows = frame[frame[TIME] >= start_ts]
    if rows.empty:
        raise DataError(
            "No rows to replay"
            + (f" on or after {start_ts.date()}" if start_ts is not None else "")
            + "."
        )
    return rows.reset_index(drop=True), start_ts


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
