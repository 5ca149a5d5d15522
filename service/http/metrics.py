"""``GET /metrics``: the service's numbers in the Prometheus text format.

Each app has its own :class:`~prometheus_client.CollectorRegistry` (never the global one,
so several services in one process, as in the tests, do not collide). One collector reads
the service at scrape time, so the numbers are always those of ``GET /health`` and
``GET /wells/{well}``:

===========================================  ================================================
``vfm_well_rolling_mape_percent{well}``      MAPE of the predictions at the last paired
                                             measurements (``rolling_window``), %
``vfm_well_interval_coverage_ratio{well}``   share of those measurements inside the 90 %
                                             interval p05..p95 (methods with intervals only)
``vfm_well_model_version{well,model,method}``  the model's version (1 per series)
``vfm_well_drift_events_total{well}``        confirmed input drifts (operating-point notices)
                                             since the service started
``vfm_well_residual_alarm_active{well}``     1 while the well's residual alarm is active
``vfm_well_residual_alarms_total{well}``     residual alarms raised since the start
``vfm_well_residual_alarm_small{well}``      1 while the active alarm's size is under the
                                           meter's usual error before it, else 0
``vfm_well_sensor_fault_active{well,sensor,kind}``  1 while the well has that instrument
                                             fault (``vfm_core.sensor_faults``)
``vfm_sensor_faults_total{sensor,kind}``     instrument faults raised, all wells (kept
                                             across restarts by the checkpoints)
``vfm_well_model_changes_total{well}``       model changes over HTTP since the start
``vfm_well_samples_total{well}``             samples handled since the start (per well)
``vfm_well_predictions_total{well}``         predictions stored since the start (per well;
                                             0 for a served well with none yet)
``vfm_well_mpfm_alarm_active{well}``         1 while the well's MPFM disagrees with its
                                             latest well test (wells with a comparison)
``vfm_well_mpfm_difference_ratio{well}``     (MPFM median - well test) / well test of it
``vfm_well_held_for_review{well}``           well tests held for review, not decided yet
``vfm_well_trial_mape_percent{well,role,outcome}``  the running (or latest) trial's MAPE, %:
                                             role ``model`` (new) and ``shadow`` (replaced)
``vfm_well_trial_pairs{well,outcome}``       that trial's paired measurements
``vfm_trials_total{outcome}``                trials ended since the start, by outcome
                                             (every outcome, 0 until it happens)
``vfm_separator_residual_sm3_per_h{separator}``  the latest allocation's reconciliation
                                             residual (total - sum of predictions), Sm3/h
``vfm_inputs_accepted_total{kind}``          accepted sensors / measurements / well_tests
``vfm_inputs_rejected_total{reason}``        refused inputs by reason (``GET /health``;
                                             every reason of ``REASONS``, 0 until it happens)
``vfm_events_total{event}``                  other events (learned, overflow, drifts, ...)
``vfm_queue_depth{worker}``                  items waiting per worker queue
``vfm_queue_capacity``                       capacity of each worker queue
``vfm_wells``                                wells served
``vfm_live_clients`` / ``vfm_live_events_dropped_total``  ``GET /events`` clients, and
                                             events dropped for slow ones
``vfm_prediction_latency_seconds``           histogram: sample arrival to stored prediction
===========================================  ================================================

A counter whose series appeared only at its first event would hide that event from
Prometheus's ``increase()`` (it needs two points), so the reasons and outcomes an alert
watches (``docker/alerts.yml``) are there from the start at 0.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from service.engine.trial import OUTCOMES
from service.errors import REASONS

__all__ = ["router", "registry_for", "ServiceCollector"]

router = APIRouter(tags=["health"])


class ServiceCollector(Collector):
    """Reads a running service (its engine, counters, observer) at every scrape."""

    def __init__(self, service: Any) -> None:
        self.service = service

    def collect(self) -> Iterator[Metric]:
        service = self.service
        snap = service.counters.snapshot()
        yield from _input_and_event_counts(snap)
        engine = service.engine
        if engine is None:
            return
        yield from _queue_gauges(service, engine)
        wells = dict(engine.wells)
        yield GaugeMetricFamily("vfm_wells", "Wells served.", value=len(wells))
        obs = engine.observer
        yield from _well_metrics(wells, obs)
        yield from (_held_for_review(wells), *_faults(wells))
        yield from _trial_metrics(wells, snap)
        yield _separator_residuals(engine)
        yield GaugeMetricFamily(
            "vfm_live_clients", "Clients of GET /events.", value=obs.subscribers
        )
        yield CounterMetricFamily(
            "vfm_live_events_dropped",
            "Live events dropped because a client read too slowly.",
            value=obs.dropped,
        )
        yield from obs.latency.collect()


def _input_and_event_counts(snap: dict[str, Any]) -> Iterator[Metric]:
    """Inputs accepted by kind, refused by reason (every reason, 0 included), other events."""
    accepted = CounterMetricFamily(
        "vfm_inputs_accepted", "Inputs accepted, by kind.", labels=["kind"]
    )
    for kind, n in sorted(snap["accepted"].items()):
        accepted.add_metric([kind], n)
    yield accepted
    rejected = CounterMetricFamily(
        "vfm_inputs_rejected", "Inputs refused, by reason (see GET /health).", labels=["reason"]
    )
    for reason in sorted(REASONS.keys() | snap["rejected"].keys()):
        rejected.add_metric([reason], snap["rejected"].get(reason, 0))
    yield rejected
    events = CounterMetricFamily(
        "vfm_events", "Other events of the engine, by name.", labels=["event"]
    )
    for name, n in sorted(snap["events"].items()):
        events.add_metric([name], n)
    yield events


def _queue_gauges(service: Any, engine: Any) -> Iterator[Metric]:
    """Each worker queue's depth, and their capacity."""
    depth = GaugeMetricFamily(
        "vfm_queue_depth", "Items waiting in each worker's queue.", labels=["worker"]
    )
    for i, n in enumerate(engine.queue_depths()):
        depth.add_metric([str(i)], n)
    yield depth
    yield GaugeMetricFamily(
        "vfm_queue_capacity",
        "Capacity of each worker queue (queues.worker_capacity).",
        value=service.settings.queues.worker_capacity,
    )


def _well_metrics(wells: dict[str, Any], obs: Any) -> Iterator[Metric]:
    """Per well: rolling error, interval coverage, model version, drifts, residual alarms,
    model changes, samples, predictions and the MPFM's agreement with the latest well test."""
    coverage = obs.coverage()
    mape = GaugeMetricFamily(
        "vfm_well_rolling_mape_percent",
        "MAPE of the predictions at the well's last paired measurements, %.",
        labels=["well"],
    )
    cover = GaugeMetricFamily(
        "vfm_well_interval_coverage_ratio",
        "Share of the well's recent learned measurements inside the predicted p05..p95 "
        "(only for methods that give intervals).",
        labels=["well"],
    )
    version = GaugeMetricFamily(
        "vfm_well_model_version",
        "The well's model version (the series' labels name its model and method).",
        labels=["well", "model", "method"],
    )
    drifts = CounterMetricFamily(
        "vfm_well_drift_events", "Confirmed drifts since the start.", labels=["well"]
    )
    alarm_active = GaugeMetricFamily(
        "vfm_well_residual_alarm_active",
        "1 while the well's residual alarm is active (any meter), else 0.",
        labels=["well"],
    )
    alarm_small = GaugeMetricFamily(
        "vfm_well_residual_alarm_small",
        "1 while the well's active residual alarm is smaller (its shift at the raise) than "
        "the meter's usual error before it: a real move that no single reading shows; else 0.",
        labels=["well"],
    )
    alarms = CounterMetricFamily(
        "vfm_well_residual_alarms",
        "Residual alarms raised since the start.",
        labels=["well"],
    )
    changes = CounterMetricFamily(
        "vfm_well_model_changes", "Model changes over HTTP since the start.", labels=["well"]
    )
    samples = CounterMetricFamily(
        "vfm_well_samples", "Sensor samples handled since the start.", labels=["well"]
    )
    predictions = CounterMetricFamily(
        "vfm_well_predictions",
        "Predictions stored since the start (a sample answered by the well's model).",
        labels=["well"],
    )
    mpfm_alarm, mpfm_diff = _mpfm_families()
    for well, st in sorted(wells.items()):
        rolling = st.rolling_mape()
        if rolling["value"] is not None:
            mape.add_metric([well], rolling["value"])
        if well in coverage:
            cover.add_metric([well], coverage[well][0])
        s = st.snapshot
        version.add_metric([well, str(s.get("model")), str(s.get("method"))], s.get("version", 0))
        drifts.add_metric([well], obs.drift_events.get(well, 0))
        if st.residual_alarm is not None:
            alarm_active.add_metric([well], 1.0 if st.residual_alarm.active else 0.0)
            small = st.residual_alarm.active and st.residual_alarm.view()["small"] is True
            alarm_small.add_metric([well], 1.0 if small else 0.0)
            alarms.add_metric([well], obs.residual_alarms.get(well, 0))
        changes.add_metric([well], obs.model_changes.get(well, 0))
        samples.add_metric([well], st.samples)
        predictions.add_metric([well], obs.predictions.get(well, 0))
        check = st.mpfm_check
        if check is not None:
            mpfm_alarm.add_metric([well], 0.0 if check["agrees"] else 1.0)
            mpfm_diff.add_metric([well], check["relative_difference"])
    yield from (mape, cover, version, drifts, alarm_active, alarm_small, alarms, changes)
    yield samples
    yield from (predictions, mpfm_alarm, mpfm_diff)


def _mpfm_families() -> tuple[GaugeMetricFamily, GaugeMetricFamily]:
    """The MPFM-against-well-test alarm and relative difference (empty families)."""
    mpfm_alarm = GaugeMetricFamily(
        "vfm_well_mpfm_alarm_active",
        "1 while the well's MPFM disagrees with its latest well test by more than "
        "alarms.mpfm_well_test_rel, else 0 (wells with a comparison only).",
        labels=["well"],
    )
    mpfm_diff = GaugeMetricFamily(
        "vfm_well_mpfm_difference_ratio",
        "(median of the MPFM readings near the latest well test - the well test) / the "
        "well test (wells with a comparison only).",
        labels=["well"],
    )
    return mpfm_alarm, mpfm_diff


def _trial_metrics(wells: dict[str, Any], snap: dict[str, Any]) -> Iterator[Metric]:
    """The trials of model changes against their shadows (service.engine.trial): each
    well's running (or latest) trial, and the trials ended by outcome."""
    trial_mape = GaugeMetricFamily(
        "vfm_well_trial_mape_percent",
        "MAPE over the paired measurements of the well's running (or latest) trial, %: "
        "role=model the new model, role=shadow the model it replaced.",
        labels=["well", "role", "outcome"],
    )
    trial_n = GaugeMetricFamily(
        "vfm_well_trial_pairs",
        "Measurements paired with both models' predictions in the well's trial.",
        labels=["well", "outcome"],
    )
    for well, st in sorted(wells.items()):
        running, ended = st.trial, list(st.trials)
        view = running.view() if running is not None else (ended[-1] if ended else None)
        if view is None:
            continue
        outcome = str(view.get("outcome"))
        for role, key in (("model", "mape"), ("shadow", "shadow_mape")):
            if view.get(key) is not None:
                trial_mape.add_metric([well, role, outcome], view[key])
        trial_n.add_metric([well, outcome], view.get("n") or 0)
    trials = CounterMetricFamily(
        "vfm_trials",
        "Trials ended since the start, by outcome (kept, rolled_back, superseded, interrupted).",
        labels=["outcome"],
    )
    by_outcome = {o: 0 for o in OUTCOMES if o != "running"}
    for name, n in snap["events"].items():
        if name.startswith("trials "):
            by_outcome[name.removeprefix("trials ")] = n
    for outcome, n in sorted(by_outcome.items()):
        trials.add_metric([outcome], n)
    yield from (trial_mape, trial_n, trials)


def _separator_residuals(engine: Any) -> GaugeMetricFamily:
    """The reconciliation residual of each separator's latest allocation (Sm3/h)."""
    gauge = GaugeMetricFamily(
        "vfm_separator_residual_sm3_per_h",
        "Latest reconciliation residual of a separator: measured total minus the sum of its "
        "wells' predictions, Sm3/h (allocations published since the start).",
        labels=["separator"],
    )
    separators = getattr(engine, "separators", None)
    if separators is not None:
        for sep, residual in sorted(separators.latest_residuals().items()):
            gauge.add_metric([sep], residual)
    return gauge


def registry_for(service: Any) -> CollectorRegistry:
    """A registry of its own for one service's app."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(service))
    return registry


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    description="The service's numbers in the Prometheus text format (per-well rolling MAPE, "
    "interval coverage, model version, drift events; accepted and refused inputs; queue "
    "depths; the prediction latency histogram). docker/prometheus.yml scrapes it.",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}}},
)
def metrics(request: Request) -> Response:
    registry: CollectorRegistry = request.app.state.metrics
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)


def _held_for_review(wells: dict[str, Any]) -> GaugeMetricFamily:
    """``vfm_well_held_for_review{well}``: the well tests held for review, not decided yet."""
    held = GaugeMetricFamily(
        "vfm_well_held_for_review",
        "Well tests of the well held for review, not decided yet (GET /wells/{well}: "
        "held_for_review; the latest 100).",
        labels=["well"],
    )
    for well, st in sorted(wells.items()):
        held.add_metric([well], len(st.held_for_review_view()))
    return held


def _faults(wells: dict[str, Any]) -> Iterator[Any]:
    """The instrument faults (vfm_core.sensor_faults): active per well, sensor and kind
    (every sensor and kind of a served well, 0 when clear) and raised per sensor and kind."""
    from vfm_core.sensor_faults import KINDS, SENSORS

    active = GaugeMetricFamily(
        "vfm_well_sensor_fault_active",
        "1 while the well's input (sensor) has an instrument fault of that kind, else 0.",
        labels=["well", "sensor", "kind"],
    )
    total = CounterMetricFamily(
        "vfm_sensor_faults",
        "Instrument faults raised per sensor and kind, all wells.",
        labels=["sensor", "kind"],
    )
    counts: dict[str, int] = {}
    for well, st in sorted(wells.items()):
        det = st.sensor_faults
        now = det.flagged_kinds()
        for sensor in SENSORS:
            for kind in KINDS:
                active.add_metric([well, sensor, kind], 1.0 if (sensor, kind) in now else 0.0)
        for key, n in dict(det.raised).items():
            counts[key] = counts.get(key, 0) + n
    for sensor in SENSORS:
        for kind in KINDS:
            total.add_metric([sensor, kind], counts.get(f"{sensor}/{kind}", 0))
    yield active
    yield total
