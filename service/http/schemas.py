"""The HTTP API's request and response bodies (the OpenAPI schema at ``/docs``).

Units: rates Sm3/h at standard conditions, pressures bar absolute, temperatures degC,
fractions 0..1, MAPE in percent; times ISO 8601 UTC.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

__all__ = [
    "ErrorOut",
    "ReviewIn",
    "HeldForReview",
    "HealthOut",
    "Parameter",
    "RollingMape",
    "MpfmCheckOut",
    "WellSummary",
    "WellOut",
    "ParameterSeries",
    "ModelMarkOut",
    "ParameterHistoryOut",
    "ModelChangeIn",
    "RollbackIn",
    "TrialOut",
    "ModelVersionOut",
    "HoldoutOut",
    "ModelChangeOut",
    "SampleOut",
    "PredictionOut",
    "MeasurementOut",
    "HistoryOut",
    "WellTestOut",
    "RetiredOut",
    "POSTED_MEASUREMENT_ERRORS",
    "measurement_body",
]


class ErrorOut(BaseModel):
    detail: str = Field(description="what was wrong, as a sentence")
    reason: str | None = Field(None, description="the rejection counter this was counted under")


#: the error answers of an endpoint that takes a measurement's JSON body (a well test, a
#: separator's reading), for its OpenAPI ``responses``
POSTED_MEASUREMENT_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut},
    403: {"model": ErrorOut},
    404: {"model": ErrorOut},
    409: {"model": ErrorOut},
    413: {"model": ErrorOut, "description": "the body is larger than http.max_body_bytes"},
    415: {"model": ErrorOut, "description": "the body is declared as something else than JSON"},
    422: {"model": ErrorOut},
    503: {"model": ErrorOut},
}


def measurement_body(schema: dict[str, Any]) -> dict[str, Any]:
    """``openapi_extra`` for an endpoint that reads its JSON body itself (bounded, checked
    as a Zenoh message is), with ``schema`` the body's JSON schema."""
    return {
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": schema}},
        }
    }


class HealthOut(BaseModel):
    status: str
    uptime_s: float
    wells: int
    received: int = Field(
        default=0, description="messages received over the bus (Zenoh or in memory) since start"
    )
    accepted: dict[str, int] = Field(
        description="accepted inputs: sensors, measurements, well_tests"
    )
    rejected: dict[str, int] = Field(description="rejected inputs by reason")
    rejected_total: int
    not_ready: int = Field(
        description="samples not answered because the well's model had no data yet"
    )
    predictions_published: int
    learned: int
    overflow: int = Field(description="messages dropped because a worker queue stayed full")
    queue_depths: list[int]
    queue_capacity: int
    busy_wells: list[int] = Field(
        default_factory=list, description="per worker, the wells with messages waiting"
    )
    retired_wells: int = 0
    limits: dict[str, Any] = Field(
        default_factory=dict, description="the input limits in force (see the config)"
    )
    pending_measurements: int
    events: dict[str, int]
    owned_wells: str = Field(
        default="*",
        description="the wells this instance owns (zenoh.wells, comma-separated; * every well)",
    )
    zenoh: dict[str, Any]
    store: str


class Parameter(BaseModel):
    """A physical parameter of the well's model (SI units), with its uncertainty where the
    learning method has one (``bayes``)."""

    value: float
    unit: str
    std: float | None = Field(
        default=None, description="posterior standard deviation (None without a Bayesian method)"
    )
    low: float | None = Field(default=None, description="lower physical bound")
    high: float | None = Field(default=None, description="upper physical bound")
    at_bound: bool | None = Field(
        default=None, description="True when the value sits at a bound (the data push past it)"
    )
    fixed: bool | None = Field(
        default=None,
        description="True when the model's specification sets the value (an effect's "
        "name:parameter=value, as the diagnosis identifies it on a hybrid's core): not learned",
    )


class RollingMape(BaseModel):
    value: float | None = Field(description="MAPE in percent over the last paired measurements")
    n: int
    window: int | None
    unit: str = "%"


class MpfmCheckOut(BaseModel):
    """The well's latest well test against its MPFM readings near it (``alarms.*``)."""

    well_test_time: str
    well_test_q_total: float = Field(description="Sm3/h")
    mpfm_median: float = Field(description="median of the MPFM readings in the window, Sm3/h")
    mpfm_readings: int
    window_s: float = Field(description="the readings lie within this many s of the well test")
    relative_difference: float = Field(description="(MPFM median - well test) / well test")
    threshold: float = Field(description="alarms.mpfm_well_test_rel")
    agrees: bool
    alarm: str | None = Field(description="the alarm's sentence while they disagree, else None")
    usual_difference: float | None = Field(
        default=None,
        description="the median relative difference of the well's earlier pairs (up to 20; "
        "None before 8): what this MPFM usually reads against the well tests",
    )
    usual_spread: float | None = Field(
        default=None, description="their robust sd in log space (at least 0.01)"
    )
    z: float | None = Field(
        default=None, description="this pair against the usual difference, in usual spreads"
    )
    shifted: bool | None = Field(
        default=None, description="|z| > 3: the MPFM moved against the well tests"
    )


class WellSummary(BaseModel):
    well: str
    model: str
    base_model: str | None = Field(
        default=None,
        description="the model without its effects (mm, hem, ham, lr, nn, last, mtl): a "
        "diagnosis of the well starts from it when it is mm, hem or ham",
    )
    effects: list[str] = Field(
        default_factory=list,
        description="the effects in the model, as PUT /wells/{well}/model takes them (a "
        "diagnosis of the well starts from them)",
    )
    method: str
    ready: bool
    version: int
    n_updates: int
    last_update: str | None
    mpfm_check: MpfmCheckOut | None = Field(
        default=None,
        description="the latest well test against the MPFM readings near it (None: no well "
        "test with MPFM readings near it yet, or the check is off)",
    )
    rejected: dict[str, int] = Field(
        default_factory=dict,
        description="this well's refused inputs by reason, since the service started",
    )


class ModelChangeIn(BaseModel):
    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    model: str | None = Field(
        default=None,
        description="base model: mm, hem, ham, lr, nn or last (default: the current one)",
    )
    effects: list[str] = Field(
        default_factory=list,
        description="effects extending mm, hem or ham, e.g. ['erosion'] or "
        "['erosion:step_at=2019-06-01', 'mypkg.effects:Scale']; [] for none",
    )
    method: str | None = Field(
        default=None, description="ol or pbl:<period> (default: the current one)"
    )
    confirm_worse: bool = Field(
        default=False,
        description="apply the change even when its held-out check says the new model is "
        "worse (without it such a change is refused with 409 and both held-out MAPEs)",
    )


class RollbackIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    version: int = Field(
        ge=0,
        le=2**62,
        description="the earlier model version to bring back (GET /wells/{well}: versions)",
    )


class ReviewIn(BaseModel):
    """The operator's decision on a measurement held for review (GET /wells/{well}:
    held_for_review)."""

    model_config = ConfigDict(extra="forbid")

    time: datetime = Field(description="the measurement's time, ISO 8601 (as held_for_review)")
    source: Literal["well_test", "mpfm"] = Field(
        default="well_test", description="the measurement's meter"
    )
    decision: Literal["accept", "reject"] = Field(
        description="accept: learn it now; reject: keep it stored, never learned"
    )


class HeldForReview(BaseModel):
    """A measurement held for review: off the model's predictive distribution and the MPFM."""

    time: str | None
    source: str
    q_total: float = Field(description="the measured rate, Sm3/h")
    predicted: float = Field(description="the model's prediction at its sample, Sm3/h")
    z: float = Field(description="log(q_total / predicted) in predictive sd")
    mpfm: float | None = Field(
        description="median of the MPFM readings near it, Sm3/h (null: none within the window)"
    )
    reason: str


class TrialOut(BaseModel):
    """A model change on trial against the model it replaced, run as a shadow."""

    model_config = ConfigDict(protected_namespaces=())

    since: str | None = Field(description="data time of the change (the well's latest sample)")
    until: str | None = Field(
        default=None, description="data time the trial is due to end (with enough pairs)"
    )
    model: str = Field(description="the new model (live)")
    shadow_model: str = Field(description="the replaced model, running as the shadow")
    method: str | None = Field(
        default=None,
        description="the new model's learning method (null in a trial of an older service)",
    )
    shadow_method: str | None = Field(
        default=None, description="the shadow's learning method (a change may be of it alone)"
    )
    n: int = Field(description="measurements paired with both models' predictions")
    mape: float | None = Field(description="MAPE (%) of the new model over those")
    shadow_mape: float | None = Field(description="MAPE (%) of the shadow over the same")
    outcome: str = Field(
        description="running | kept | rolled_back | superseded | interrupted (a restart "
        "without the shadow)"
    )
    version: int | None = Field(default=None, description="the new model's version at the change")
    shadow_version: int | None = None
    blocks: int | None = Field(default=None, description="blocks of data time with pairs")
    p_value: float | None = Field(
        default=None, description="one-sided p of 'the shadow is better' (block t-test)"
    )
    mean_diff: float | None = Field(
        default=None, description="mean of the block means of APE(new) - APE(shadow), points"
    )
    rule: str | None = Field(default=None, description="the rule, as a sentence")
    min_pairs: int | None = None
    last_paired: str | None = None
    ended: str | None = Field(default=None, description="data time the trial ended")
    why: str | None = Field(default=None, description="why it ended so, as a sentence")


class ModelVersionOut(BaseModel):
    """A model the well ran before, kept for a rollback."""

    model_config = ConfigDict(protected_namespaces=())

    version: int = Field(description="its version when it was replaced (POST .../rollback)")
    model: str
    effects: list[str] = Field(default_factory=list)
    method: str
    replaced: str | None = Field(description="data time it was replaced")
    note: str = Field(description="why it was replaced")


class HoldoutOut(BaseModel):
    holdout_rows: int = Field(description="latest stored measurements held out to compare")
    holdout_from: str | None = None
    before: float | None = Field(
        default=None,
        description="MAPE (%) of the current model, fitted on the older rows, then learning "
        "with its method over the held-out ones (predict, then learn each)",
    )
    after: float | None = Field(
        default=None,
        description="MAPE (%) of the new model, fitted on the same rows, then learning with "
        "its method over the held-out ones",
    )
    protocol: str | None = Field(
        default=None,
        description="replayed: each model learns with its method over the held-out rows, as "
        "the service runs it (s54; before, both were fitted once and never updated)",
    )
    unit: str = "%"
    fit_s: float | None = Field(default=None, description="time the fits took, s")
    confirmed_worse: bool | None = Field(
        default=None,
        description="true when the check said worse and the change was applied as confirmed "
        "(confirm_worse); null when the check had nothing to compare",
    )


class ModelChangeOut(BaseModel):
    model_config = ConfigDict(protected_namespaces=())

    time: str
    model_before: str
    model_after: str
    effects: list[str] = Field(default_factory=list, description="the new model's effects")
    method: str
    version_before: int
    version_after: int
    holdout: HoldoutOut
    caught_up: int = Field(
        default=0,
        description="measurements learned while the new model was fitted, taught to it before the swap",
    )
    rolling_mape_before: float | None = Field(
        description="rolling MAPE (%) of the replaced model at the change"
    )
    kind: str = Field(
        default="change", description="change | rollback (over HTTP) | trial rollback"
    )
    note: str | None = Field(default=None, description="why, as a sentence")
    rolled_back_to: int | None = Field(default=None, description="a rollback's version")
    relearned: int | None = Field(
        default=None, description="a rollback: measurements re-learned since the version"
    )
    trial: TrialOut | None = Field(
        default=None, description="the change's reply: the trial it started (None: none)"
    )


class WellOut(WellSummary):
    model_config = ConfigDict(protected_namespaces=())

    parameters: dict[str, Parameter] = Field(description="physical parameters, SI units")
    rolling_mape: RollingMape
    measurements_remembered: int = Field(
        description="measurements the model keeps for retrains and model changes"
    )
    model_changes: list[ModelChangeOut] = Field(
        description="models set over HTTP, oldest first; the rolling MAPE restarts at each"
    )
    drift: dict[str, Any] = Field(
        description="the T^2 test on the inputs: a notice that the operating point left the "
        "training data, not an alarm"
    )
    residual_alarm: dict[str, Any] | None = Field(
        default=None,
        description="the alarm on the model's standardised residuals: enabled, active, "
        "statistic, threshold, since, direction, source, arl0, k, accept_periods, alarm_on_return, streams (per "
        "meter), events (with closed: cleared | accepted | reset once ended; reset: ended "
        "by a model change, which restarts the detectors), and while active which_moved: "
        "for an alarm on the MPFM's stream, what the well tests compared since it began say "
        "read together (well_test_time: the latest, z: their mean move's, moved: meter | "
        "well | unclear, text, alarm_shift: the alarm's relative size at its raise, meter_z: "
        "the mean move's distance from it in spreads, n_well_tests, z_latest: the latest "
        "pair's z alone), else "
        "null; and while it is null for such an alarm, awaiting_well_test: what will tell "
        "(last_well_test, typical_gap_days, due, pairs: well tests compared before the "
        "alarm, overdue: the well's data is past due, text); shift: the active alarm's "
        "relative size (measured against the model, at its raise; null when unknown), "
        "shift_se its standard error (log), onset: when the change began (the reading "
        "the shift is measured from; since is when the alarm was raised)",
    )
    held_for_review: list[HeldForReview] = Field(
        default_factory=list,
        description="well tests held for review, not learned until accepted, oldest first "
        "(POST /wells/{well}/measurements/review decides)",
    )
    latest_prediction: dict[str, Any] | None = Field(
        default=None,
        description="the latest stored prediction (after a restart, read back from the "
        "store until a new one comes): time, q_total "
        "and its 90 % interval q_total_p05, q_total_p95 (Sm3/h; null for a method without "
        "one); null before any",
    )
    sensor_faults: list[dict[str, Any]] = Field(
        default_factory=list,
        description="instrument faults of the well's inputs, oldest first (the latest 50): "
        "sensor, kind (frozen, spike, drift, offset, out_of_range), start, end (null while "
        "active), evidence, detected, alarm (whether it raises an alarm: the page's alarm line, "
        "the VfmSensorFault alert; an input's own offset and a spike are shown only)",
    )
    fallback: list[dict[str, Any]] | None = Field(
        default=None,
        description="the inputs replaced by a stand-in at the latest sample while flagged "
        "(frozen or out of range): sensor, kind, value, measured, spread, low, high (units of "
        "the input: fraction, bar a, degC), since; null when every input was used as read",
    )
    samples: int = Field(description="samples accepted since start")
    measurements: int = Field(description="measurements accepted since start")
    last_sample_time: str | None
    pending_measurements: int
    trial: TrialOut | None = Field(
        default=None,
        description="the running trial of the last model change against its shadow, else the "
        "latest ended one (None: no trial yet)",
    )
    trials: list[TrialOut] = Field(
        default_factory=list, description="the ended trials, oldest first (the latest 10)"
    )
    versions: list[ModelVersionOut] = Field(
        default_factory=list,
        description="earlier models kept for a rollback, newest first (trial.keep_versions)",
    )


class ParameterSeries(BaseModel):
    """One physical parameter over time (SI units), oldest first."""

    unit: str
    low: float | None = Field(default=None, description="lower physical bound")
    high: float | None = Field(default=None, description="upper physical bound")
    time: list[str] = Field(description="data time of the measurement learned before, UTC")
    value: list[float | None]
    std: list[float | None] = Field(
        description="posterior standard deviation (None without a Bayesian method)"
    )
    version: list[int]


class ModelMarkOut(BaseModel):
    time: str
    model_before: str
    model_after: str


class ParameterHistoryOut(BaseModel):
    well: str
    since: str
    until: str
    rows: int = Field(description="recorded rows returned")
    truncated: bool = Field(description="more rows lay in the window; the latest are returned")
    parameters: dict[str, ParameterSeries]
    model_changes: list[ModelMarkOut] = Field(
        description="where the recorded model's name changes between two rows (its parameters "
        "change too: an effect adds its own)"
    )


class SampleOut(BaseModel):
    time: str
    choke: float
    p_up: float
    p_down: float
    t_up: float
    eta_gas: float
    eta_oil: float
    received: str


class PredictionOut(BaseModel):
    time: str
    q_total: float
    q_gas: float | None
    q_oil: float | None
    q_water: float | None
    version: int | None
    q_total_std: float | None = Field(
        default=None, description="predictive standard deviation, Sm3/h (methods with intervals)"
    )
    q_total_p05: float | None = Field(default=None, description="5 % quantile, Sm3/h")
    q_total_p95: float | None = Field(default=None, description="95 % quantile, Sm3/h")


class MeasurementOut(BaseModel):
    time: str
    source: str
    q_total: float
    received: str
    via: str
    status: str = Field(description="pending | learned | unpaired")
    paired_sample_time: str | None
    predicted: float | None = Field(
        description="the prediction at the paired sample, before learning"
    )
    version_after: int | None


class HistoryOut(BaseModel):
    well: str
    start: str
    end: str
    samples: list[SampleOut]
    predictions: list[PredictionOut]
    measurements: list[MeasurementOut]
    truncated: bool


class WellTestOut(BaseModel):
    well: str
    time: str
    q_total: float
    stored: bool = True
    status: str = Field(
        description="learned, pending (waiting for the sensor sample at its time), review "
        "(held for review, not learned) or rejected (on review)"
    )
    message: str
    paired_sample_time: str | None
    before: dict[str, float | None] = Field(
        description="prediction at the paired sample before learning, Sm3/h"
    )
    after: dict[str, float | None] = Field(
        description="prediction at the same inputs after learning, Sm3/h"
    )
    version_before: int
    version_after: int
    model_changed: bool


class RetiredOut(BaseModel):
    well: str
    retired: str = Field(description="when it was retired, ISO 8601 UTC")
    purged: bool = Field(description="True: every row of the well was deleted")
    samples: int = Field(description="samples accepted since the service started")
    measurements: int = Field(description="measurements accepted since the service started")
    version: int = Field(description="the model's version at retirement")
