"""The trial of a model change: the replaced model goes on as a *shadow* and both are compared.

After ``PUT /wells/{well}/model`` swaps a new model in, the model it replaced keeps running
on the well's worker as if nothing had changed: it predicts every sensor sample of the
well (:meth:`Trial.on_sample`, with its own scheduled retrains) and learns every paired
measurement with its own method (:meth:`Trial.on_learned`). At each paired measurement
whose sample came after the change, both absolute percentage errors are taken: the live
model's (the prediction the service published at that sample) and the shadow's (its
prediction at the same sample, made before it learned the measurement). Their paired
differences are summed per block of ``trial.block_s`` of data time (a day).

The trial ends at the first paired measurement whose sample is ``trial.duration_s`` of
data time (sample timestamps, not wall-clock) after the change, once ``trial.min_pairs``
pairs are in (or at ``trial.max_duration_s`` with what there is). Then the rule
(:func:`decide`) keeps the change, or rolls it back: the shadow, which has learned
everything the live model learned, is swapped in with a higher version.

The rule (``trial.rule = "block_t"``): a one-sided Student t-test of the block means of
``d = APE(new) - APE(shadow)`` against 0; a rollback when ``p < trial.alpha`` (0.05). Why
this test: the two models are scored on the *same* measurements, so their errors are
paired and the meter's own error (common to both) cancels in ``d``; but an MPFM's error
is autocorrelated over hours (the same operating point, a slow drift of the meter), so
the per-measurement differences are not independent and a test on them would be far too
confident. Means over daily blocks are close to independent (the method of batch means)
and, over a few dozen measurements each, close to normal, which the t-test needs. One
sided, because the change is kept unless it is shown to be worse: the operator chose it,
and its held-out check spoke for it (or was overridden knowingly). Fewer than two blocks
allow no test: the change is kept and the trial says so. ``trial.rule = "keep"`` never
rolls back (the trial only reports).

A trial is part of the well's checkpoint side-car (:meth:`Trial.state`: its blocks and the
shadow's own checkpoint, base64), so a restart restores it and re-learns the shadow from
the store with the live model; a trial whose shadow cannot be restored ends
``interrupted`` (the change is kept). A new model change or a rollback while a trial
runs ends it ``superseded``. Ended trials are written to the store (``trials``), counted
(``trials kept`` ...) and logged.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import time
from collections import OrderedDict
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from scipy import stats

from service.config import Settings, TrialSettings
from service.engine.residual_alarms import alarm_op
from service.store import (
    InsertModelVersion,
    InsertTrial,
    Op,
    PruneModelVersions,
)
from vfm_core.errors import VFMError
from vfm_core.learning.streaming import Learner, WellLearner
from vfm_core.timeutil import from_ns, iso

if TYPE_CHECKING:
    from service.engine.parameters import ParameterHistory
    from service.engine.state import Sample, WellState


class Checkpoints(Protocol):
    """What a trial needs of :class:`service.engine.checkpoints.Checkpoints` (a protocol,
    so that this module imports neither it nor :mod:`service.engine.learning`, which import
    this one)."""

    @property
    def parameters(self) -> ParameterHistory: ...

    def ops(self, st: WellState) -> list[Op]: ...


class _Counters(Protocol):
    def event(self, name: str, n: int = 1) -> None: ...


class Learning(Protocol):
    """What a trial needs of :class:`service.engine.learning.Learning`."""

    @property
    def checkpoints(self) -> Checkpoints: ...

    @property
    def settings(self) -> Settings: ...

    @property
    def counters(self) -> _Counters: ...

    def catch_up(self, learner: Learner, time_ns: int) -> bool: ...


__all__ = ["OUTCOMES", "Trial", "block_test", "decide", "install", "rule_text", "version_ops"]

logger = logging.getLogger("vfm.service.engine")

#: what a trial's ``outcome`` can be
OUTCOMES = ("running", "kept", "rolled_back", "superseded", "interrupted")

#: the shadow's predictions kept per trial, by sample time, until their measurement comes
_PREDICTIONS = 512

_NS = 1_000_000_000


def block_test(blocks: Sequence[tuple[int, float, float]]) -> dict[str, Any]:
    """One-sided paired test that the shadow is better, on block means.

    ``blocks``: per block of data time, (pairs, sum of the new model's absolute
    percentage errors, sum of the shadow's), errors as fractions. Returns the number of
    blocks, the mean of the block means of ``APE(new) - APE(shadow)`` in percentage
    points, the t statistic and the one-sided p-value of ``mean > 0`` (None with fewer
    than two blocks)."""
    d = np.array([(sn - ss) / n for n, sn, ss in blocks if n > 0], dtype=float)
    k = int(d.size)
    out: dict[str, Any] = {"blocks": k, "mean_diff": None, "t": None, "p_value": None}
    if k == 0:
        return out
    mean = float(d.mean())
    out["mean_diff"] = mean * 100.0
    if k < 2:
        return out
    sd = float(d.std(ddof=1))
    if sd <= 1e-15 * max(1.0, abs(mean)):  # identical blocks: the sign decides
        out["t"] = math.inf if mean > 0 else (-math.inf if mean < 0 else 0.0)
        out["p_value"] = 0.0 if mean > 0 else 1.0
        return out
    t = mean / (sd / math.sqrt(k))
    out["t"] = t
    out["p_value"] = float(stats.t.sf(t, k - 1))
    return out


def rule_text(rule: str, alpha: float, block_s: float) -> str:
    """The rule as a sentence (what GET /wells/{well} shows under ``trial.rule``)."""
    if rule == "keep":
        return "keep: the change is never rolled back automatically; the trial only reports."
    block = f"{block_s / 86_400:g}-day" if block_s % 86_400 == 0 else f"{block_s:g}-s"
    return (
        f"block_t: one-sided paired t-test on {block} block means of APE(new) - APE(shadow); "
        f"rolled back when p < {alpha:g} (the shadow better beyond noise), else kept."
    )


def decide(rule: str, alpha: float, blocks: Sequence[tuple[int, float, float]]) -> dict[str, Any]:
    """The end of a trial: ``outcome`` ("kept" or "rolled_back"), the test, and why (a sentence)."""
    test = block_test(blocks)
    p = test["p_value"]
    if rule == "keep":
        return {**test, "outcome": "kept", "why": "The rule is keep: never rolled back."}
    if p is None:
        return {
            **test,
            "outcome": "kept",
            "why": f"Paired measurements in {test['blocks']} block(s): too few to test; kept.",
        }
    if p < alpha:
        return {
            **test,
            "outcome": "rolled_back",
            "why": f"The shadow was better by {test['mean_diff']:.2f} points of APE on average "
            f"(p = {p:.3g} < {alpha:g} over {test['blocks']} blocks); rolled back.",
        }
    return {
        **test,
        "outcome": "kept",
        "why": f"The shadow was not better beyond noise (p = {p:.3g} >= {alpha:g} over "
        f"{test['blocks']} blocks; mean difference {test['mean_diff']:+.2f} points); kept.",
    }


class Trial:
    """One well's trial of a model change against its shadow (see the module docstring).

    Owned by the well's worker, as :class:`~service.engine.state.WellState` is; the HTTP
    API reads :meth:`view` (plain numbers, read whole)."""

    def __init__(
        self,
        *,
        well: str,
        since_ns: int,
        model: str,
        shadow_model: str,
        version: int,
        shadow_version: int,
        shadow: Learner | None,
        settings: TrialSettings,
        method: str | None = None,
        shadow_method: str | None = None,
    ) -> None:
        self.well = well
        self.since_ns = since_ns
        self.model = model
        self.shadow_model = shadow_model
        self.version = version  # the new model's version at the change
        self.shadow_version = shadow_version  # the shadow's at the change
        # the learning methods (a change of method alone keeps the model's name)
        self.method = method
        self.shadow_method = shadow_method
        self.shadow = shadow
        self.duration_ns = int(settings.duration_s * _NS)
        self.max_ns = int(max(settings.max_duration_s, settings.duration_s) * _NS)
        self.block_ns = max(int(settings.block_s * _NS), 1)
        self.min_pairs = settings.min_pairs
        self.alpha = settings.alpha
        self.rule = settings.rule
        self.block_s = settings.block_s
        #: block index -> [pairs, sum APE new, sum APE shadow] (fractions)
        self.blocks: dict[int, list[float]] = {}
        self.n = 0
        self.sum_new = 0.0
        self.sum_shadow = 0.0
        self.last_ns: int | None = None  # the latest paired sample's time
        self.outcome = "running"
        self.ended_ns: int | None = None
        self.test: dict[str, Any] = {}
        self.why = ""
        self.predictions: OrderedDict[int, float | None] = OrderedDict()

    # -- on the worker ----------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.outcome == "running" and self.shadow is not None

    def on_sample(self, learning: Learning, time_ns: int, inputs: Sequence[float]) -> None:
        """The shadow predicts a sample of the well (its scheduled retrains run first, as
        for the live model); its answer waits for the sample's measurement."""
        shadow = self.shadow
        if shadow is None:
            return
        try:
            learning.catch_up(shadow, time_ns)
            q = shadow.predict(list(inputs), from_ns(time_ns)).get("q_total")
        except Exception as exc:  # the shadow must never stop the live model
            self._lost(f"its prediction failed ({exc})")
            return
        preds = self.predictions
        preds[time_ns] = q if q is not None and math.isfinite(q) else None
        if len(preds) > _PREDICTIONS:
            preds.popitem(last=False)

    def on_learned(
        self,
        learning: Learning,
        st: WellState,
        sample: Sample,
        q_total: float,
        time_ns: int,
        source: str,
        ops: list[Op],
    ) -> None:
        """A measurement (Sm3/h, at ``time_ns``) paired with ``sample`` was learned by the
        live model: the shadow learns it too; both errors at the sample are paired; the
        trial ends when due (:meth:`conclude`)."""
        shadow = self.shadow
        if shadow is None:
            return
        try:
            if sample.time_ns in self.predictions:
                q_shadow = self.predictions[sample.time_ns]
            else:  # a sample the shadow did not see live (a restart's re-learning)
                learning.catch_up(shadow, sample.time_ns)
                q_shadow = shadow.predict(list(sample.inputs), from_ns(sample.time_ns)).get(
                    "q_total"
                )
            learning.catch_up(shadow, time_ns)
            shadow.learn(list(sample.inputs), q_total, from_ns(time_ns), source)
        except Exception as exc:
            self._lost(f"it failed to learn ({exc})")
            self._end(st, ops, "interrupted", time_ns, learning)
            _checkpoint(learning, st, ops)
            return
        q_new = sample.predicted
        if (
            sample.time_ns > self.since_ns
            and q_new is not None
            and q_shadow is not None
            and math.isfinite(q_shadow)
            and q_total
        ):
            a_new = abs(q_new - q_total) / abs(q_total)
            a_shadow = abs(q_shadow - q_total) / abs(q_total)
            block = self.blocks.setdefault(
                (sample.time_ns - self.since_ns) // self.block_ns, [0, 0.0, 0.0]
            )
            block[0] += 1
            block[1] += a_new
            block[2] += a_shadow
            self.n += 1
            self.sum_new += a_new
            self.sum_shadow += a_shadow
            self.last_ns = sample.time_ns
        elapsed = sample.time_ns - self.since_ns
        if (elapsed >= self.duration_ns and self.n >= self.min_pairs) or elapsed >= self.max_ns:
            self.conclude(learning, st, ops, sample.time_ns)

    def conclude(self, learning: Learning, st: WellState, ops: list[Op], when_ns: int) -> None:
        """Apply the rule; keep the change or swap the shadow back in (recorded)."""
        verdict = decide(self.rule, self.alpha, [tuple(b) for b in self.blocks.values()])  # type: ignore[misc]
        self.test = {k: verdict[k] for k in ("blocks", "mean_diff", "t", "p_value")}
        self.why = verdict["why"]
        outcome = verdict["outcome"]
        if outcome == "rolled_back" and st.catch_up is not None:
            # a model change is being fitted from the live model: let it land first
            return
        shadow = self.shadow
        self._end(st, ops, outcome, when_ns, learning)
        if outcome != "rolled_back" or shadow is None:
            _checkpoint(learning, st, ops)
            return
        install(
            st,
            shadow,
            learning.checkpoints,
            ops,
            when_ns,
            kind="trial rollback",
            note=f"rolled back by its trial: {self.why.rstrip('.').removesuffix('; rolled back')}.",
            keep_versions=learning.settings.trial.keep_versions,
            extra={"trial": self.summary()},
            learn_seq=st.learn_seq + 1,  # the measurement being learned is recorded next
        )

    def supersede(self, st: WellState, ops: list[Op], when_ns: int | None, why: str) -> None:
        """The model is replaced by another change or a rollback while the trial runs."""
        self.why = why
        self._end(st, ops, "superseded", when_ns, None)

    def _lost(self, why: str) -> None:
        logger.warning("The trial of %s lost its shadow %s: %s.", self.well, self.shadow_model, why)
        self.why = f"The shadow {self.shadow_model} was lost: {why}; the change is kept."

    def _end(
        self,
        st: WellState,
        ops: list[Op],
        outcome: str,
        when_ns: int | None,
        learning: Learning | None,
    ) -> None:
        self.outcome = outcome
        self.ended_ns = when_ns
        self.shadow = None
        self.predictions.clear()
        if st.trial is self:
            st.trial = None
        summary = self.summary()
        st.trials.append(summary)
        ops.append(
            InsertTrial(
                well=self.well,
                created_ns=time.time_ns(),
                since_ns=self.since_ns,
                ended_ns=when_ns,
                model=self.model,
                shadow_model=self.shadow_model,
                outcome=outcome,
                summary=json.dumps(summary),
            )
        )
        if learning is not None:
            learning.counters.event(f"trials {outcome}")
        named = self.method != self.shadow_method  # a change of method: name both
        logger.info(
            "Trial of %s on %s: %s (MAPE %s %% against the shadow %s's %s %% over %d paired "
            "measurement(s)). %s",
            _label(self.model, self.method if named else None),
            self.well,
            outcome.replace("_", " "),
            _fmt(summary["mape"]),
            _label(self.shadow_model, self.shadow_method if named else None),
            _fmt(summary["shadow_mape"]),
            self.n,
            self.why,
        )

    # -- what the API reads ---------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """The trial as GET /wells/{well} shows it (``trial``); MAPEs in %."""
        n = self.n
        return {
            "since": iso(self.since_ns),
            "until": iso(self.since_ns + self.duration_ns),
            "model": self.model,
            "shadow_model": self.shadow_model,
            "method": self.method,
            "shadow_method": self.shadow_method,
            "version": self.version,
            "shadow_version": self.shadow_version,
            "n": n,
            "mape": self.sum_new / n * 100.0 if n else None,
            "shadow_mape": self.sum_shadow / n * 100.0 if n else None,
            "outcome": self.outcome,
            "blocks": len(self.blocks),
            "p_value": self.test.get("p_value"),
            "mean_diff": self.test.get("mean_diff"),
            "rule": rule_text(self.rule, self.alpha, self.block_s),
            "min_pairs": self.min_pairs,
            "last_paired": iso(self.last_ns),
            "ended": iso(self.ended_ns),
            "why": self.why or None,
        }

    def view(self) -> dict[str, Any]:
        """:meth:`summary`, with the test so far while the trial runs."""
        out = self.summary()
        blocks = list(self.blocks.values())  # one step: the worker may add a block meanwhile
        if self.outcome == "running" and len(blocks) >= 2:
            test = block_test([tuple(b) for b in blocks])  # type: ignore[misc]
            out["p_value"], out["mean_diff"] = test["p_value"], test["mean_diff"]
        return out

    # -- checkpoints ------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Everything to resume the trial, JSON-safe (the shadow's checkpoint as base64)."""
        return {
            "well": self.well,
            "since_ns": self.since_ns,
            "model": self.model,
            "shadow_model": self.shadow_model,
            "method": self.method,
            "shadow_method": self.shadow_method,
            "version": self.version,
            "shadow_version": self.shadow_version,
            "settings": {
                "duration_s": self.duration_ns / _NS,
                "max_duration_s": self.max_ns / _NS,
                "block_s": self.block_s,
                "min_pairs": self.min_pairs,
                "alpha": self.alpha,
                "rule": self.rule,
            },
            "blocks": [[k, *v] for k, v in self.blocks.items()],
            "last_ns": self.last_ns,
            "shadow": (
                base64.b64encode(self.shadow.checkpoint()).decode("ascii")
                if self.shadow is not None
                else None
            ),
        }

    @classmethod
    def restore(cls, data: dict[str, Any]) -> tuple[Trial, str | None]:
        """A trial from :meth:`state`; and why its shadow could not be restored (None if it was)."""
        s = data["settings"]
        settings = TrialSettings(
            duration_s=s["duration_s"],
            max_duration_s=s["max_duration_s"],
            block_s=s["block_s"],
            min_pairs=s["min_pairs"],
            alpha=s["alpha"],
            rule=s["rule"],
        )
        trial = cls(
            well=data["well"],
            since_ns=int(data["since_ns"]),
            model=data["model"],
            shadow_model=data["shadow_model"],
            version=int(data["version"]),
            shadow_version=int(data["shadow_version"]),
            shadow=None,
            settings=settings,
            method=data.get("method"),  # None in the state of an older service
            shadow_method=data.get("shadow_method"),
        )
        for k, n, sn, ss in data.get("blocks", []):
            trial.blocks[int(k)] = [int(n), float(sn), float(ss)]
            trial.n += int(n)
            trial.sum_new += float(sn)
            trial.sum_shadow += float(ss)
        trial.last_ns = data.get("last_ns")
        blob = data.get("shadow")
        if not blob:
            return trial, "its checkpoint holds no shadow"
        try:
            trial.shadow = WellLearner.restore(base64.b64decode(blob))
        except (VFMError, ValueError) as exc:
            return trial, f"the shadow's checkpoint cannot be read ({exc})"
        return trial, None


def version_ops(
    st: WellState,
    learner: Learner,
    when_ns: int | None,
    note: str,
    keep: int,
    learn_seq: int | None = None,
) -> list[Op]:
    """The writes that keep ``learner`` (the model being replaced, which has learned the
    well's measurements up to ``learn_seq``, by default the well's) as an earlier version."""
    return [
        InsertModelVersion(
            well=st.well,
            version=learner.version,
            created_ns=time.time_ns(),
            data_time_ns=when_ns,
            learn_seq=st.learn_seq if learn_seq is None else learn_seq,
            model=learner.name,
            method=learner.method.text,
            spec=json.dumps([learner.model_name, list(learner.effects), learner.method.text]),
            note=note,
            blob=learner.checkpoint(),
        ),
        PruneModelVersions(well=st.well, keep=keep),
    ]


def install(
    st: WellState,
    new: Learner,
    checkpoints: Checkpoints,
    ops: list[Op],
    when_ns: int | None,
    *,
    kind: str,
    note: str,
    keep_versions: int,
    config: list[Any] | None = None,
    holdout: dict[str, Any] | None = None,
    caught_up: int = 0,
    extra: dict[str, Any] | None = None,
    learn_seq: int | None = None,
) -> dict[str, Any]:
    """Swap ``new`` in for the well's model, on its worker: the replaced model is kept as an
    earlier version, ``new`` gets a higher version, the change is recorded (in
    ``st.model_changes``, the checkpoint side-car) and the rolling error restarts. The
    writes (the earlier version, the checkpoint, the parameters) go to ``ops``; ``kind``:
    change | rollback | trial rollback; ``when_ns``: data time (the well's latest sample);
    ``learn_seq``: the measurements both models have learned (by default the well's; one
    more when this runs within a learning step, before it is recorded)."""
    old = st.learner
    new.renumber(old.version + 1)
    before = st.rolling_mape()
    change: dict[str, Any] = {
        "time": iso(time.time_ns()),
        "model_before": old.name,
        "model_after": new.name,
        "effects": list(new.effects),
        "method": new.method.text,
        "version_before": old.version,
        "version_after": new.version,
        "holdout": holdout if holdout is not None else {"holdout_rows": 0, "unit": "%"},
        "caught_up": caught_up,
        "rolling_mape_before": before["value"],
        "config": config
        if config is not None
        else (st.model_changes[-1].get("config") if st.model_changes else None),
        "kind": kind,
        "note": note,
        "data_time": iso(when_ns),
        **(extra or {}),
    }
    seq = st.learn_seq if learn_seq is None else learn_seq
    if old.checkpoint_group is None:  # a checkpoint of its own: it can be brought back alone
        ops.extend(version_ops(st, old, when_ns, note, keep_versions, seq))
    st.learner = new
    st.model_changes.append(change)
    st.errors.clear()  # the rolling error from now on is the new model's
    ops.extend(_restart_alarm(st, when_ns))
    st.refresh()
    recorded, st.learn_seq = st.learn_seq, seq
    try:
        ops.extend(checkpoints.ops(st))
    finally:
        st.learn_seq = recorded
    ops.extend(checkpoints.parameters.ops(st, when_ns if when_ns is not None else time.time_ns()))
    logger.info(
        "Model of %s: %s from %s (version %d) to %s (version %d). %s",
        st.well,
        kind,
        old.name,
        old.version,
        new.name,
        new.version,
        note,
    )
    return change


def _restart_alarm(st: WellState, when_ns: int | None) -> list[Op]:
    """A model change restarts the well's residual alarm: the new model's residuals are a
    new stream (``docs/guide/alarms.md``). An alarm still active ends, recorded at
    ``when_ns`` (data time, epoch ns) as ended by the change."""
    alarm = st.residual_alarm
    if alarm is None:
        return []
    at = when_ns if when_ns is not None else time.time_ns()
    ops: list[Op] = []
    for transition in alarm.reset():
        ops.append(alarm_op(st.well, at, transition))
        logger.info(
            "Residual alarm on %s (%s) ended at %s by the model change: the new model's "
            "residuals are tested afresh.",
            st.well,
            transition[1],
            iso(at),
        )
    return ops


def _checkpoint(learning: Learning, st: WellState, ops: list[Op]) -> None:
    """A checkpoint of the well now that its trial ended (so that a restart does not run it
    again), within a learning step: the measurement being learned is recorded next."""
    recorded = st.learn_seq
    st.learn_seq = recorded + 1
    try:
        ops.extend(learning.checkpoints.ops(st))
    finally:
        st.learn_seq = recorded


def _label(model: str, method: str | None) -> str:
    """A model as the log names it: with its method when the trial changed the method."""
    return model if method is None else f"{model} ({method})"


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"
