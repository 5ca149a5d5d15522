"""Predicting and learning for one well, on its worker thread, and the drift test.

* :meth:`Learning.predict_many`: the rates for the sensor samples of a batch, many wells in
  one model call (with ``pbl``, a retrain that is due runs first, on the calendar of
  ``vfm evaluate``); None for a well whose model cannot answer yet.
* :meth:`Learning.learn_paired`: learn from a measurement paired with its sample, record
  it as learned (its place in the learning order, the sample, the prediction made there)
  and answer a waiting well-test caller with the prediction before and after. The
  learning step of a learner whose model is its own (not
  :attr:`~vfm_core.learning.streaming.Learner.shares_model`) is deferred to the end of
  the worker's batch (:meth:`Learning.run_deferred`), where the batch's learns of all
  wells run in one :func:`vfm_core.learning.streaming.learn_many` call (the wells' ``ol`` or
  ``bayes`` updates stacked into one multi-well update, each well's result what its own
  ``learn`` gives); the worker runs them earlier whenever anything else of such a well
  comes (its next sample, another measurement, a model change), so each well sees the
  order of one-by-one handling. A step that moves other wells' models too (a separator's
  member with kept cross-covariances, :class:`JointLearning`) is taken at once.
* :meth:`Learning.apply`: the learning step itself, also used to re-learn after a
  checkpoint on start: learn, score the prediction made at the sample (the rolling
  error), feed the well's residual alarm (:mod:`service.engine.residual_alarms`: an
  alarm that begins or ends is stored, counted and logged) and its streaming Hotelling
  T^2 test on the inputs (an "operating point outside the training data" notice, stored
  as a drift event; with ``drift.on_drift = "retrain"`` it retrains the well).

A worker must never hang on one well. Each fit of a live well has a wall-clock budget
(``model.retrain_budget_s``, see :func:`service.engine.learners.train_settings`) on top of its
iteration caps; a method's retrain period is at least ``model.min_retrain_period_s``; and
when a sample or measurement comes more than ``model.max_catch_up_retrains`` periods
after the next scheduled retrain (a well back from a long gap), one retrain on everything
so far replaces the missed ones, keeping the calendar's phase (the missed ones would all
train on the same data). Steps slower than a second are counted (``slow learning steps``)
and logged.

This module uses only the :class:`vfm_core.learning.streaming.Learner` protocol, which
:class:`vfm_core.learning.streaming.WellLearner` and :class:`vfm_core.learning.field.FieldWell` (a
well of the field-wide ``mtl``) both keep (a block of samples in one call is asked
only of a learner whose model predicting cannot change; another refuses it).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from service.config import Settings
from service.engine.checkpoints import Checkpoints
from service.engine.items import Batch, DeferredLearn
from service.engine.learners import Learner
from service.engine.pools import Pools, coupled
from service.engine.residual_alarms import alarm_op
from service.engine.state import Pending, Sample, WellState, WellTestResult
from service.inputs import Counters
from service.store import InsertDriftEvent, MarkLearned, Op
from vfm_core.learning.streaming import learn_many, predict_many
from vfm_core.sensor_faults import Fallback, fallback_points, residual_noise, widened_rates
from vfm_core.timeutil import from_ns, iso

__all__ = ["Learning"]

logger = logging.getLogger("vfm.service.engine")

Rates = dict[str, float | None]
#: samples predicted with a stand-in whose answers wait for their measurement (a well's
#: MPFM reading pairs with one of its latest samples)
_STAND_INS_KEPT = 64


class JointLearning(Protocol):
    """Wells whose learning step moves other wells' models: a separator's wells with kept
    cross-covariances (:class:`service.engine.separators.Separators`). Such a well learns
    at once, never deferred, and the samples taken before its measurement are predicted
    first (as a field-wide well's)."""

    def moves_others(self, well: str) -> bool:
        """Whether ``well``'s learning step may move other wells' models."""

    def before_learn(self, st: WellState, time_ns: int) -> object | None:
        """What the carry needs of the wells before ``st`` learns a measurement at
        ``time_ns`` (None: nothing to carry)."""

    def carry(self, mark: object) -> bool:
        """After the learning step: carry it to the other wells; whether any moved."""

    def carried(self, st: WellState, ops: list[Op], time_ns: int) -> None:
        """After the step is recorded: the writes that keep the moved wells' state."""


def _wants_sd(st: WellState) -> bool:
    """True when the residual alarm standardises by the prediction's sd (a method that
    gives one, ``bayes``): the prediction before learning is then made for it."""
    method = getattr(st.learner, "method", None)
    return st.residual_alarm is not None and bool(getattr(method, "intervals", False))


class Learning:
    """Prediction, learning, rolling error and drift for the wells of the workers."""

    #: True: the learning steps of a worker batch run together (:meth:`run_deferred`);
    #: False: each at once, one by one (the same results; the tests compare the two)
    batch_learns: bool = True

    def __init__(self, settings: Settings, counters: Counters, checkpoints: Checkpoints) -> None:
        self.settings = settings
        self.counters = counters
        self.checkpoints = checkpoints
        self.max_catch_up = settings.model.max_catch_up_retrains
        self._last_slow_log = 0.0
        #: wells whose learning moves others' models (set by the separators; None: none)
        self.joint: JointLearning | None = None
        #: the calibration pools of ``bayes:cal_pool=on`` (each well's learner joins its
        #: pool through :attr:`WellState.learner <service.engine.state.WellState.learner>`)
        self.pools = Pools()

    def moves_others(self, well: str) -> bool:
        """Whether ``well``'s learning step moves other wells' models (see
        :class:`JointLearning`); the worker then predicts the samples before it first."""
        return self.joint is not None and self.joint.moves_others(well)

    @staticmethod
    def pools_now(st: WellState, source: str) -> bool:
        """Whether learning a ``source`` measurement of ``st`` moves the other wells'
        intervals: a well test of a learner in a calibration pool (``bayes:cal_pool=on``)
        publishes its errors there. Such a step is taken at once, never deferred, and the
        samples taken before it are predicted first, so that every later sample of every
        well of the worker reads the pool after it (as one by one)."""
        return source == "well_test" and coupled(st.learner)

    def catch_up(self, learner: Learner, time_ns: int) -> bool:
        """Before a step at ``time_ns``: one retrain instead of more than
        ``model.max_catch_up_retrains`` missed ones (see the module docstring). True if it ran."""
        method = learner.method
        due = method.next_due()
        period = getattr(method, "period", None)
        if due is None or period is None or time_ns < due:
            return False
        period_ns = int(period.value)
        if period_ns <= 0:
            return False
        missed = (time_ns - due) // period_ns + 1
        if missed <= self.max_catch_up:
            return False
        learner.retrain(from_ns(time_ns))
        method.start(due + (missed - 1) * period_ns)  # the next one where the calendar puts it
        self.counters.event("retrains collapsed")
        logger.info(
            "%s: %d scheduled retrains were due at once (a gap in its data); one retrain on "
            "everything so far replaced them.",
            learner.well,
            missed,
        )
        return True

    def _timed(self, st: WellState, started: float, what: str) -> None:
        took = time.monotonic() - started
        if took < 1.0:
            return
        self.counters.event("slow learning steps")
        if time.monotonic() - self._last_slow_log > 60.0:
            self._last_slow_log = time.monotonic()
            logger.warning(
                "%s of %s took %.1f s (model.retrain_budget_s bounds each fit); other wells of "
                "its worker waited meanwhile.",
                what,
                st.well,
                took,
            )

    def predict_many(
        self, states: list[WellState], inputs: list[tuple[float, ...]], times_ns: list[int]
    ) -> list[Rates | None | BaseException]:
        """Rates (Sm3/h) for samples of different wells in one model call (see
        :func:`vfm_core.learning.streaming.predict_many`), or None while a well's model has no
        (finite) answer; a well whose step failed gets its exception in its place.
        ``times_ns``: each sample's time, epoch ns."""
        started = time.monotonic()
        out: list[Rates | None | BaseException] = [None] * len(states)
        go: list[int] = []
        for i, (st, t) in enumerate(zip(states, times_ns, strict=True)):
            try:
                self.catch_up(st.learner, t)
                go.append(i)
            except Exception as exc:
                out[i] = exc
        everyone = len(go) == len(states)
        answers = predict_many(
            [st.learner for st in states] if everyone else [states[i].learner for i in go],
            inputs if everyone else [inputs[i] for i in go],
            times_ns if everyone else [times_ns[i] for i in go],
            return_exceptions=True,
        )
        if states:
            what = (
                f"A batch of {len(states)} prediction(s) (with their scheduled retrains), the first"
            )
            self._timed(states[0], started, what)
        for i, rates in zip(go, answers, strict=True):
            if isinstance(rates, BaseException):
                out[i] = rates
                continue
            q_total = rates.get("q_total")
            out[i] = None if q_total is None or not math.isfinite(q_total) else rates
        return out

    def fallback(
        self,
        st: WellState,
        inputs: Sequence[float],
        rates: Rates | None,
        used: Sequence[Fallback],
        time_ns: int | None = None,
    ) -> tuple[Rates | None, list[dict[str, Any]] | None]:
        """Keep predicting while an input is flagged: when inputs of the sample have an open
        fault of a kind that stands in (:data:`vfm_core.sensor_faults.FALLBACK_KINDS`;
        ``used``: their stand-ins, found when the sample was fed to the detectors,
        :meth:`WellState.watch_sample <service.engine.state.WellState.watch_sample>`), the
        rates (Sm3/h) predicted with their fallback values in place of the readings, the
        interval widened to cover the rates at the ends of the fallbacks' spans
        (:func:`vfm_core.sensor_faults.widened_rates`), and what stood in (the message's and
        ``GET /wells/{well}``'s ``fallback``, kept as ``st.fallback``). Otherwise ``rates``
        as they are and None (no stand-in, no rates: the model is not ready, or no finite
        answer at the stand-ins). The raw inputs are stored unchanged either way.

        The model is asked right after the sample's own prediction, its features and
        clock at the sample: the worker (:mod:`service.engine.worker`) stacks no later
        sample of the well into the prediction call of a sample with a stand-in. The
        stand-ins and answers are kept by the sample's time ``time_ns`` (epoch ns) for
        its measured rate to witness (:meth:`follow_rate`)."""
        st.fallback = None
        if not used or not rates:
            return rates, None
        try:
            answers = [st.learner.predict(p) for p in fallback_points(inputs, used)]
        except Exception as exc:  # the measured input's prediction is still an answer
            logger.warning("The fallback prediction of %s failed: %s", st.well, exc)
            return rates, None
        out = widened_rates(answers)
        q_total = out.get("q_total")
        if q_total is None or not math.isfinite(q_total):
            return rates, None
        st.fallback = [f.as_dict() for f in used]
        if time_ns is not None:
            kept = st.stand_in_answers
            kept[int(time_ns)] = (tuple(used), answers)
            while len(kept) > _STAND_INS_KEPT:
                kept.popitem(last=False)
        return out, st.fallback

    def follow_rate(self, st: WellState, time_ns: int, q_total: float, source: str) -> bool:
        """An MPFM rate (Sm3/h) measured at the sample at ``time_ns`` (epoch ns) that was
        predicted with a stand-in: taken as a witness of the stood-in input
        (:meth:`WellSensorFaults.follow_rate <vfm_core.sensor_faults.WellSensorFaults.follow_rate>`;
        the meter's bias and noise from the well's last learned MPFM log residuals,
        :func:`~vfm_core.sensor_faults.residual_noise`), held or not: the input's stand-in
        moves, the model does not. True when the stand-in moved. Other sources are not
        taken (a well test is rare, and its bias is not the MPFM's)."""
        if source != "mpfm":
            return False
        kept = st.stand_in_answers.pop(int(time_ns), None)
        if kept is None or not st.watch_faults:
            return False
        used, answers = kept
        noise = residual_noise(st.mpfm_residuals)
        return st.sensor_faults.follow_rate(time_ns, used, answers, q_total, noise)

    def predict_block(
        self, st: WellState, inputs: np.ndarray, times_ns: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Rates (Sm3/h) for a block of one well's samples in one model call (see
        :meth:`vfm_core.learning.streaming.WellLearner.predict_block`), timed as a learning step."""
        started = time.monotonic()
        out: dict[str, np.ndarray] = st.learner.predict_block(inputs, times_ns)
        self._timed(st, started, f"A block of {len(times_ns)} prediction(s)")
        return out

    def learn_paired(self, st: WellState, p: Pending, sample: Sample, b: Batch) -> None:
        """Learn from a measurement paired with ``sample``; record it; answer its caller.

        The learning step of a learner whose model is its own (not
        :attr:`~vfm_core.learning.streaming.Learner.shares_model`: nothing else reads it meanwhile)
        waits in ``b`` for the batch's one learning call (:meth:`run_deferred`); everything
        around it runs in the order of learning at once. A field-wide well learns at once:
        its step moves the other wells' model, in arrival order."""
        if st.well in b.learn_wells:  # the well's earlier measurement is learned first
            self.run_deferred(b)
        learner = st.learner
        version_before = learner.version
        # the prediction before learning: for the caller, and its sd for the residual alarm
        wants = p.future is not None or _wants_sd(st)
        before = learner.predict(list(sample.inputs)) if wants else {}
        if (
            self.batch_learns
            and not learner.shares_model
            and not self.moves_others(st.well)
            and not self.pools_now(st, p.source)
        ):
            self.catch_up(learner, p.time_ns)
            b.learns.append(DeferredLearn(st, p, sample, version_before, before))
            b.learn_wells.add(st.well)
            return
        moved = self.apply(st, sample, p.q_total, p.time_ns, b.ops, p.source)
        self._record(st, p, sample, b, version_before, before)
        if moved and self.joint is not None:  # the other wells' state, kept with this one's
            self.joint.carried(st, b.ops, p.time_ns)

    def run_deferred(self, b: Batch) -> None:
        """Run the learning steps waiting in ``b``, all wells in one
        :func:`~vfm_core.learning.streaming.learn_many` call, then record each (as
        :meth:`learn_paired` would have right away). A well whose step fails is counted
        as an internal error and its caller answered with the error; the others go on."""
        learns = b.learns
        if not learns:
            return
        b.learns, b.learn_wells = [], set()
        started = time.monotonic()
        try:
            results: list[bool | BaseException] = learn_many(
                [d.st.learner for d in learns],
                [list(d.sample.inputs) for d in learns],
                [d.pending.q_total for d in learns],
                [from_ns(d.pending.time_ns) for d in learns],
                [d.pending.source for d in learns],
                return_exceptions=True,
            )
        except Exception as exc:  # pragma: no cover - learn_many answers errors in place
            results = [exc] * len(learns)
        self._timed(learns[0].st, started, f"A batch of {len(learns)} learning step(s), the first")
        for d, result in zip(learns, results, strict=True):
            p = d.pending
            try:
                if isinstance(result, BaseException):
                    raise result
                sd = d.before.get("q_total_std") if d.before else None
                self._after_step(d.st, d.sample, p.q_total, p.time_ns, b.ops, p.source, sd)
                self._record(d.st, p, d.sample, b, d.version_before, d.before)
            except Exception as exc:  # one well's failure must not stop the others
                logger.exception(
                    "Unexpected error learning the %s measurement of %s: %s",
                    p.source,
                    d.st.well,
                    exc,
                )
                self.counters.event("internal errors")
                b.answer(p.future, exc)

    def _record(
        self,
        st: WellState,
        p: Pending,
        sample: Sample,
        b: Batch,
        version_before: int,
        before: Rates,
    ) -> None:
        """After the learning step: record the measurement as learned, answer its caller."""
        learner = st.learner
        st.learn_seq += 1
        self.checkpoints.changed(st, b.ops, p.time_ns)
        b.ops.append(
            MarkLearned(
                well=st.well,
                source=p.source,
                time_ns=p.time_ns,
                learn_seq=st.learn_seq,
                sample=sample,
                version_after=learner.version,
            )
        )
        self.counters.event("learned")
        if p.future is None:
            return
        after = learner.predict(list(sample.inputs))
        changed = learner.version != version_before
        b.answer(
            p.future,
            WellTestResult(
                st.well,
                iso(p.time_ns) or "",
                p.q_total,
                "learned",
                "Stored and learned from: the model was updated."
                if changed
                else learner.deferred_note(),
                paired_sample_time=iso(sample.time_ns),
                before=before,
                after=after,
                version_before=version_before,
                version_after=learner.version,
                model_changed=changed,
            ),
        )

    def apply(
        self,
        st: WellState,
        sample: Sample,
        q_total: float,
        time_ns: int,
        ops: list[Op],
        source: str = "mpfm",
    ) -> bool:
        """Learn, score the earlier prediction, run the drift test (also used when
        re-learning). True when the step was carried to other wells (:class:`JointLearning`)."""
        learner = st.learner
        started = time.monotonic()
        self.catch_up(learner, time_ns)
        sd = learner.predict(list(sample.inputs)).get("q_total_std") if _wants_sd(st) else None
        mark = self.joint.before_learn(st, time_ns) if self.joint is not None else None
        learner.learn(list(sample.inputs), q_total, from_ns(time_ns), source)
        moved = mark is not None and self.joint is not None and self.joint.carry(mark)
        self._timed(st, started, "Learning a measurement")
        self._after_step(st, sample, q_total, time_ns, ops, source, sd)
        return moved

    def _after_step(
        self,
        st: WellState,
        sample: Sample,
        q_total: float,
        time_ns: int,
        ops: list[Op],
        source: str,
        sd: float | None = None,
    ) -> None:
        """What follows the learning step: note it for a model change in progress, score
        the earlier prediction, run the residual alarm (``sd``: the predictive sd, Sm3/h,
        at the sample before learning, for a method that gives one) and the T^2 input test."""
        if st.catch_up is not None:
            st.catch_up.append((sample.inputs, q_total, time_ns, source))
        if sample.predicted is not None and q_total:
            st.errors.append(abs(sample.predicted - q_total) / abs(q_total))
        if st.trial is not None:  # the shadow learns it too (service.engine.trial)
            st.trial.on_learned(self, st, sample, q_total, time_ns, source, ops)
        if st.residual_alarm is not None:
            self._residual(st, sample, q_total, time_ns, ops, source, sd)
        st.learned_inputs.append(sample.inputs)
        det = st.detector
        if det is None:
            return
        was = bool(det.drift_detected)
        det.update(list(sample.inputs))
        if det.drift_detected and not was:
            self._on_drift(st, time_ns, ops)

    def _on_drift(self, st: WellState, time_ns: int, ops: list[Op]) -> None:
        det = st.detector
        assert det is not None
        action = "recorded"
        if self.settings.drift.on_drift == "retrain":
            st.learner.retrain(from_ns(time_ns))
            action = "retrained"
        event: dict[str, Any] = {
            "time": iso(time_ns),
            "statistic": float(det.statistic),
            "p_value": float(det.p_value),
            "action": action,
        }
        st.drift_events.append(event)
        ops.append(
            InsertDriftEvent(
                well=st.well,
                time_ns=time_ns,
                statistic=event["statistic"],
                p_value=event["p_value"],
                action=action,
            )
        )
        logger.info(
            "Operating point of %s outside its training data at %s (input T2 = %.1f, p = %.2g); "
            "%s.",
            st.well,
            event["time"],
            event["statistic"],
            event["p_value"],
            action,
        )
        self.counters.event("drifts")
        ref = np.asarray(st.learned_inputs, dtype=float)
        det.reset(ref if len(ref) >= self.settings.drift.reference_size else None)

    def _residual(
        self,
        st: WellState,
        sample: Sample,
        q_total: float,
        time_ns: int,
        ops: list[Op],
        source: str,
        sd: float | None,
    ) -> None:
        """Feed the residual alarm; store, count and log an alarm that begins or ends."""
        alarm = st.residual_alarm
        assert alarm is not None
        for kind, src, event in alarm.update(source, q_total, sample.predicted, sd, time_ns):
            ops.append(alarm_op(st.well, time_ns, (kind, src, event)))
            if kind == "start":
                self.counters.event("residual alarms")
                logger.warning(
                    "Residual alarm on %s from %s: the %s readings are %s the model's "
                    "predictions beyond their usual scatter (CUSUM %.1f > %.2f); the model "
                    "does not follow a change of the well or of the meter.",
                    st.well,
                    event["start"],
                    src,
                    "above" if event["direction"] == "high" else "below",
                    event["statistic"],
                    event["threshold"],
                )
            elif event.get("closed") == "accepted":
                logger.info(
                    "Residual alarm on %s (%s) closed at %s: the residuals held their new "
                    "level for %d periods; accepted as the new level, the test restarts "
                    "from it.",
                    st.well,
                    src,
                    event["end"],
                    alarm.settings.accept_periods,
                )
            else:
                logger.info(
                    "Residual alarm on %s (%s) ended at %s: the residuals are back in control.",
                    st.well,
                    src,
                    event["end"],
                )

    def seed_reference(self, st: WellState, inputs: np.ndarray) -> None:
        """After a history fit: the latest measured rows' inputs [n, 6] as the drift reference."""
        if st.detector is None:
            return
        ref = inputs[-self.settings.drift.reference_size :]
        st.learned_inputs.extend(tuple(map(float, r)) for r in ref)
        if len(ref) >= self.settings.drift.reference_size:
            st.detector.reset(ref)
