"""The well's residual alarm: has the model's error changed beyond what the learner absorbs?

Per well, one :class:`vfm_core.residual_alarm.ResidualCusum` per meter (``mpfm``,
``well_test``; created at a meter's first measurement), fed on the well's worker after
each learning step with the measurement's residual against the prediction made at its
sample (standardised by the predictive sd for a method that gives one, ``bayes``; the
relative error ``ln(measured / predicted)`` otherwise). The rule, its parameters
(``residual_alarm.*`` in the settings) and the measured false-alarm rates and delays are
in ``docs/guide/alarms.md``.

An alarm that begins or ends is a row of the store's ``residual_alarms`` table (event
``alarm`` on ``GET /events``), a log line, and counts in ``/metrics``
(``vfm_well_residual_alarm_active{well}``, ``vfm_well_residual_alarms_total{well}``).
GET /wells/{well} shows :meth:`WellResidualAlarm.view` as ``residual_alarm``.
"""

from __future__ import annotations

from collections import deque
from typing import Any

from service.config import ResidualAlarmSettings
from service.store import InsertResidualAlarm
from vfm_core.residual_alarm import (
    AlarmSize,
    ResidualCusum,
    alarm_size,
    cusum_threshold,
    standardised_residual,
)
from vfm_core.timeutil import iso

__all__ = ["WellResidualAlarm", "Transition", "disabled_view", "alarm_op"]

#: (kind "start" | "end", source, the event as the API shows it)
Transition = tuple[str, str, dict[str, Any]]

_EVENTS_KEPT = 20


#: the names of :meth:`WellResidualAlarm._design`'s settings in a detector's saved state
_DESIGN_KEYS = (
    "arl0",
    "k",
    "period_s",
    "window",
    "min_periods",
    "clip",
    "lags",
    "scale",
    "accept_periods",
    "alarm_on_return",
)


def alarm_op(well: str, time_ns: int, transition: Transition) -> InsertResidualAlarm:
    """The store's row of an alarm that began or ended (``transition``) on ``well`` at
    ``time_ns`` (data time, epoch ns)."""
    kind, source, event = transition
    return InsertResidualAlarm(
        well=well,
        time_ns=time_ns,
        source=source,
        kind=kind,
        direction=str(event["direction"]),
        statistic=float(event["statistic"]),
        threshold=float(event["threshold"]),
    )


class WellResidualAlarm:
    """The residual alarms of one well, one detector per meter (owned by its worker)."""

    def __init__(self, settings: ResidualAlarmSettings) -> None:
        self.settings = settings
        self.detectors: dict[str, ResidualCusum] = {}
        self.events: deque[dict[str, Any]] = deque(maxlen=_EVENTS_KEPT)
        self._open: dict[str, dict[str, Any]] = {}  # source -> its active event
        #: per meter, the readings' log ratios to the model that size an alarm
        self.sizes: dict[str, AlarmSize] = {}
        self.alarms = 0  # alarms raised since start

    def _period_s(self, source: str) -> float:
        s = self.settings
        return s.mpfm_period_s if source == "mpfm" else s.well_test_period_s

    def _design(self, source: str) -> tuple[Any, ...]:
        """The detector's settings for ``source``, in :class:`ResidualCusum`'s order (and
        :data:`_DESIGN_KEYS`' in its saved state)."""
        s = self.settings
        period = self._period_s(source)
        return (
            s.arl0,
            s.k,
            period,
            s.window,
            s.min_periods,
            s.clip,
            s.lags,
            s.scale,
            s.accept_periods,
            s.alarm_on_return,
        )

    def detector(self, source: str) -> ResidualCusum:
        det = self.detectors.get(source)
        if det is None:
            det = ResidualCusum(*self._design(source))
            self.detectors[source] = det
        return det

    def update(
        self,
        source: str,
        measured: float,
        predicted: float | None,
        sd: float | None,
        time_ns: int,
    ) -> list[Transition]:
        """One learned measurement (Sm3/h, data time epoch ns) and the prediction made at
        its sample with its predictive sd (Sm3/h; None without one): what began or ended."""
        if predicted is None:
            return []
        residual = standardised_residual(float(measured), float(predicted), sd)
        size = self.sizes.setdefault(source, AlarmSize())
        size.add(time_ns, float(measured), float(predicted))
        det = self.detector(source)
        before = len(det.events)
        was = det.alarm
        det.update(residual, time_ns)
        out: list[Transition] = []
        if was and not det.alarm:  # one period closes per update: an end or a start
            event = self._open.pop(source, None)
            if event is not None:
                end_ns = det.events[-1].end_ns
                event["end"] = iso(end_ns if end_ns is not None else time_ns)
                event["closed"] = det.events[-1].closed
                out.append(("end", source, event))
        if len(det.events) > before:
            new = det.events[-1]
            self.alarms += 1
            event = {
                "source": source,
                "start": iso(new.start_ns),
                "end": None,
                "closed": None,
                "direction": new.direction,
                "statistic": float(new.statistic),
                "threshold": float(det.threshold),
            }
            onset = new.start_ns if new.onset_ns is None else new.onset_ns
            sized = size.at_raise(onset, new.start_ns)
            # the change's time: the scan's, where the size is known (the CUSUM's onset is
            # often days early: its statistic may leave zero by chance before the change)
            event["onset"] = iso(onset if sized is None else sized["onset_ns"])
            event["shift"] = None if sized is None else sized["shift"]
            event["shift_se"] = None if sized is None else sized["se"]
            event["typical_error"] = None if sized is None else sized["typical"]
            event["small"] = alarm_size(event["shift"], event["typical_error"])["small"]
            self.events.append(event)
            self._open[source] = event
            out.append(("start", source, event))
        return out

    @property
    def active(self) -> bool:
        return any(d.alarm for d in self.detectors.values())

    def reset(self) -> list[Transition]:
        """Start over at a model change: the new model's residuals are a new stream, tested
        once each meter has ``min_periods`` periods of them again (the change's trial judges
        the new model meanwhile). Past events stay listed; an active alarm ends with end and
        closed ``"reset"`` and is returned as an ``end`` transition."""
        out: list[Transition] = []
        for source, event in self._open.items():
            event["end"] = event.get("end") or "reset"
            event["closed"] = "reset"
            out.append(("end", source, event))
        self._open.clear()
        self.detectors.clear()
        self.sizes.clear()
        return out

    def state(self) -> dict[str, Any]:
        """Plain values (JSON) for the well's checkpoint side-car: each meter's detector and
        the events listed, so that a restart resumes the test where it was (the self-starting
        scale would otherwise need ``min_periods`` periods again before it tests)."""
        return {
            "detectors": {src: det.state_dict() for src, det in self.detectors.items()},
            "events": list(self.events),
            "sizes": {src: size.state() for src, size in self.sizes.items()},
        }

    def restore(self, data: dict[str, Any]) -> None:
        """Resume from :meth:`state`. A detector saved under other settings (``arl0``, ``k``,
        the periods, the window ...) starts afresh: its statistic would mean something else.
        One saved before s46 (no ``accept_periods``) or s47 (no ``alarm_on_return``)
        resumes under the current settings: they change what happens after an alarm, not
        the statistic."""
        missing = {
            "accept_periods": self.settings.accept_periods,
            "alarm_on_return": self.settings.alarm_on_return,
        }
        for source, saved in (data.get("detectors") or {}).items():
            if tuple(saved.get(k, missing.get(k)) for k in _DESIGN_KEYS) != self._design(source):
                continue
            det = self.detector(source)
            det.load_state_dict(saved)
        for source, saved in (data.get("sizes") or {}).items():  # (none before s51)
            self.sizes.setdefault(str(source), AlarmSize()).restore(saved)
        self.events.extend(dict(e) for e in data.get("events") or [])
        for event in self.events:  # the alarms still active go on
            resumed = self.detectors.get(str(event.get("source")))
            if event.get("end") is None and resumed is not None and resumed.alarm:
                self._open[str(event["source"])] = event

    def view(self) -> dict[str, Any]:
        """What GET /wells/{well} shows as ``residual_alarm``."""
        s = self.settings
        streams: dict[str, Any] = {}
        lead: tuple[float, str] | None = None
        for source, det in sorted(self.detectors.items()):
            stat = float(det.statistic)
            event = self._open.get(source, {}) if det.alarm else {}
            streams[source] = {
                "active": det.alarm,
                "statistic": stat,
                "threshold": float(det.threshold),
                "direction": det.direction,
                "since": iso(det.since_ns),
                "ready": det.ready,
                "readings": det.n_readings,
                "periods": det.n_periods,
                "period_s": det.period_s,
                "shift": event.get("shift"),
                "shift_se": event.get("shift_se"),
                "onset": event.get("onset"),
                **alarm_size(event.get("shift"), event.get("typical_error")),
            }
            rank = (stat / det.threshold if det.threshold > 0 else 0.0) + (2.0 if det.alarm else 0)
            if lead is None or rank > lead[0]:
                lead = (rank, source)
        top = streams.get(lead[1]) if lead is not None else None
        active = [st for st in streams.values() if st["active"]]
        first = min(active, key=lambda st: st["since"] or "") if active else None
        return {
            "enabled": True,
            "active": bool(active),
            "statistic": top["statistic"] if top else None,
            "threshold": top["threshold"] if top else float(self.detector_threshold()),
            "since": first["since"] if first else None,
            "direction": first["direction"] if first else None,
            "shift": first["shift"] if first else None,
            "shift_se": first["shift_se"] if first else None,
            "onset": first["onset"] if first else None,
            "small": first["small"] if first else None,
            "typical_error_percent": first["typical_error_percent"] if first else None,
            "source": (lead[1] if lead is not None and active else None),
            "arl0": s.arl0,
            "k": s.k,
            "accept_periods": s.accept_periods,
            "alarm_on_return": s.alarm_on_return,
            "streams": streams,
            "events": list(self.events),
        }

    def detector_threshold(self) -> float:
        return cusum_threshold(self.settings.arl0, self.settings.k)


def disabled_view() -> dict[str, Any]:
    """``residual_alarm`` when ``residual_alarm.enabled`` is false."""
    return {"enabled": False, "active": False, "note": "disabled"}
