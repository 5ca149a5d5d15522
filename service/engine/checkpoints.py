"""Checkpoints of each well's model (and its parameter history), written in the same
transactions as the data.

A checkpoint is :meth:`vfm_core.learning.streaming.WellLearner.checkpoint` bytes (tensors and
plain values, never pickle) with a JSON side-car: the drift detector's state and
reference inputs, the drift events, the model changes made over HTTP, the model's
specification ``[model, effects, method]``, and the trial of the last change with its
shadow's own checkpoint (base64) while it runs (:mod:`service.engine.trial`; restored with
the configured retrain budget, or ended ``interrupted`` when it cannot be), and the residual
alarm's detectors (:mod:`service.engine.residual_alarms`). It is written every
``store.checkpoint_every`` model updates, after a model change and at a clean stop, and
the latest ``store.keep_checkpoints`` of a well are kept. Since it goes into the same
transaction as the data, the store never holds a model that is ahead of its data.

On start, :func:`usable` says whether a well's latest checkpoint may be restored under
the configured model (see :mod:`service.engine.recovery`).

A well of a field-wide model (``mtl``) checkpoints the whole field: its blob is the
:meth:`vfm_core.learning.field.FieldLearner.checkpoint` snapshot (every well's part, the
shared network, the method, the round still open and how many measurements of each well
it holds). Such a learner names the field as its checkpoint group
(:attr:`vfm_core.learning.streaming.Learner.checkpoint_group`). Since every step of the shared
model moves every well's version, a snapshot is due when the *group* has moved
``store.checkpoint_every`` versions since its last one, and it is written once, in the
row of the well whose message made it due (at a clean stop, once for the group); recovery
restores the newest one.
"""

from __future__ import annotations

import json
import logging
import time
import weakref
from collections.abc import Iterable
from typing import Any

from service.config import ModelSettings, Settings
from service.engine.learners import apply_budget
from service.engine.parameters import ParameterHistory
from service.engine.state import WellState
from service.store import CheckpointRow, InsertCheckpoint, Op, PruneCheckpoints
from vfm_core.effects import effect_spec, resolve_effects
from vfm_core.errors import VFMError

__all__ = ["Checkpoints", "configured_spec", "usable"]

logger = logging.getLogger("vfm.service.engine")


def configured_spec(settings: Settings) -> list[Any]:
    """The configured model as [name, effect specs, method], to compare with checkpoints."""
    m = settings.model
    return [m.name, [effect_spec(c) for c in resolve_effects(m.effects)], m.method]


def usable(row: CheckpointRow, spec: list[Any], configured: str) -> tuple[bool, str]:
    """Whether a well's checkpoint may be restored under the configured model, and why.

    Yes when it holds the configured model, effects (with their settings) and method; or
    when its model was chosen over HTTP and the config has not changed since that choice
    (a later edit of the config wins, and is said so).
    """
    try:
        extra = json.loads(row.extra)
    except ValueError:
        extra = {}
    saved = extra.get("spec") if isinstance(extra, dict) else None
    if saved is None:  # checkpoints before effects: compare names
        return (row.model, row.method) == (configured, spec[2]), ""
    if saved == spec:
        return True, ""
    changes = extra.get("model_changes") or []
    if changes and changes[-1].get("config") == spec:
        return True, (
            f"keeps {row.model} ({row.method}), chosen over HTTP at {changes[-1].get('time')}; "
            "edit the config's model to replace it"
        )
    if changes:
        return False, (
            f"the config changed since {row.model} was chosen over HTTP; building {configured} "
            "from the history and the stored measurements"
        )
    return False, ""


class Checkpoints:
    """Writes each well's checkpoint when due, and reads its side-car back."""

    def __init__(self, settings: Settings) -> None:
        self.model = settings.model
        self.every = settings.store.checkpoint_every
        self.keep = settings.store.keep_checkpoints
        self.parameters = ParameterHistory(settings)
        #: per checkpoint group (a field-wide learner), the version of its latest snapshot
        self._group_saved: weakref.WeakKeyDictionary[object, int] = weakref.WeakKeyDictionary()

    def saved_version(self, st: WellState) -> int:
        """The version the well's model had at its last checkpoint (for a learner of a
        checkpoint group, a field-wide model, the group's at its last snapshot, whichever
        well's row holds it)."""
        group = st.learner.checkpoint_group
        if group is not None:
            return self._group_saved.get(group, st.checkpoint_version)
        return st.checkpoint_version

    def once(self, st: WellState) -> list[Op]:
        """:meth:`ops` of a well whose model was built at start-up; for a checkpoint group (a
        field-wide model) only the first of its wells writes (one snapshot holds them all)."""
        group = st.learner.checkpoint_group
        if group is not None and group in self._group_saved:
            return []
        return self.ops(st)

    def ops(self, st: WellState) -> list[Op]:
        """The writes of a checkpoint of the well's model now (and of pruning older ones)."""
        learner = st.learner
        group = learner.checkpoint_group
        if group is not None:
            self._group_saved[group] = learner.version
        extra = {
            "drift": st.detector.state_dict() if st.detector is not None else None,
            "learned_inputs": [list(x) for x in st.learned_inputs],
            "drift_events": list(st.drift_events),
            "model_changes": list(st.model_changes),
            "spec": [learner.model_name, list(learner.effects), learner.method.text],
            # the running trial with its shadow's checkpoint, and the ended ones
            # (service.engine.trial)
            "trial": st.trial.state() if st.trial is not None else None,
            "trials": list(st.trials),
            # the residual alarm's detectors (service.engine.residual_alarms)
            "residual_alarm": st.residual_alarm.state() if st.residual_alarm is not None else None,
            # the instrument-fault detectors (vfm_core.sensor_faults)
            "sensor_faults": st.sensor_faults.state(),
        }
        st.checkpoint_version = learner.version
        return [
            InsertCheckpoint(
                well=st.well,
                created_ns=time.time_ns(),
                version=learner.version,
                learn_seq=st.learn_seq,
                model=learner.name,
                method=learner.method.text,
                blob=learner.checkpoint(),
                extra=json.dumps(extra),
            ),
            PruneCheckpoints(well=st.well, keep=self.keep),
        ]

    def changed(self, st: WellState, ops: list[Op], time_ns: int | None = None) -> None:
        """The model's version moved: checkpoint when due, refresh what the API shows, and
        record the parameters at data time ``time_ns`` when due (see
        :mod:`service.engine.parameters`)."""
        if st.learner.version - self.saved_version(st) >= self.every:
            ops.extend(self.ops(st))
        st.refresh()
        if time_ns is not None:
            self.parameters.maybe(st, time_ns, ops)

    def final_ops(self, wells: Iterable[WellState]) -> list[Op]:
        """Checkpoints of every well whose model moved since its last one (at a clean stop)."""
        ops: list[Op] = []
        for st in wells:
            if st.learner.version != self.saved_version(st):
                ops.extend(self.ops(st))
        return ops

    def restore_side_car(self, st: WellState, extra: str) -> None:
        """Put a checkpoint's side-car back: drift state and events, learned inputs, changes."""
        try:
            data = json.loads(extra)
        except ValueError:
            return
        if st.detector is not None and data.get("drift"):
            try:
                st.detector.load_state_dict(data["drift"])
            except (KeyError, TypeError, ValueError, VFMError) as exc:
                logger.warning(
                    "Drift state of %s not restored (%s); the detector starts over.", st.well, exc
                )
        st.learned_inputs.extend(tuple(x) for x in data.get("learned_inputs", []))
        st.drift_events.extend(data.get("drift_events", []))
        st.model_changes.extend(data.get("model_changes", []))
        st.trials.extend(data.get("trials", []))
        if data.get("residual_alarm") and st.residual_alarm is not None:
            st.residual_alarm.restore(data["residual_alarm"])
        if data.get("sensor_faults"):
            try:
                st.sensor_faults.restore(data["sensor_faults"])
            except (KeyError, TypeError, ValueError, VFMError) as exc:
                logger.warning(
                    "Sensor-fault state of %s not restored (%s); it starts over.", st.well, exc
                )
        if data.get("trial"):
            _restore_trial(st, data["trial"], self.model)


def _restore_trial(st: WellState, data: dict[str, Any], model: ModelSettings) -> None:
    """Put a running trial back with its shadow, which then re-learns from the store with
    the live model; one whose shadow cannot be restored ends ``interrupted`` (the change kept)."""
    from service.engine.trial import Trial

    try:
        trial, problem = Trial.restore(data)
    except (KeyError, TypeError, ValueError) as exc:
        logger.warning("The trial of %s could not be restored (%s); it ends.", st.well, exc)
        return
    if problem is None:
        assert trial.shadow is not None
        apply_budget(trial.shadow, model)  # the configured retrain budget and memory bound
        st.trial = trial
        return
    trial.outcome = "interrupted"
    trial.why = f"The trial was interrupted by a restart: {problem}; the change is kept."
    st.trials.append(trial.summary())
    logger.warning("Trial of %s on %s: %s", trial.model, st.well, trial.why)
