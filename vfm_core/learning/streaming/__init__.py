"""One well's model and learning method, fed one sample at a time: the core of the service.

:class:`WellLearner` wraps a per-well model (any registered model but the field-wide
``mtl``) with its learning method (:mod:`vfm_core.learning`). ``predict`` answers a sensor
sample with rates; ``learn`` takes a measured rate paired with the sample's inputs and
hands it to the method, which learns at once (``ol``) or at its next retrain
(``pbl:<period>``). The same models and the same method objects run here as in
:func:`vfm_core.jobs.study.run_prequential`, so a replay through the service reproduces
``vfm evaluate``.

A learner may extend ``mm``, ``hem`` or ``ham`` with effects (:mod:`vfm_core.effects`);
the standard features they use (years on stream, cumulative throughput, water cut) are
kept up to date sample by sample by a :class:`vfm_core.features.FeatureTracker`.
:meth:`WellLearner.refit_as` builds a different model on the same remembered history.

:func:`predict_many` and :func:`learn_many` do the same for many wells' samples and
measurements at once (the service's worker batches), with the wells' models stacked into
one multi-well model call; each well's results equal its own ``predict`` and ``learn``.

State is tensors and plain values only: :meth:`WellLearner.checkpoint` returns bytes
that :meth:`WellLearner.restore` reads back with ``torch.load(weights_only=True)``.

Modules: :mod:`~vfm_core.learning.streaming.learner` (:class:`WellLearner`, one well's
bookkeeping: features, memory, versions, retrains due, checkpoints),
:mod:`~vfm_core.learning.streaming.samples` (a sample as plain numbers and as a batch),
:mod:`~vfm_core.learning.streaming.phases` (the phase split); this module holds the many-wells
calls, which group the learners by their methods' group keys and leave the stacking to
the methods (:meth:`vfm_core.learning.LearningMethod.predict_group`,
:meth:`~vfm_core.learning.LearningMethod.learn_group`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from datetime import datetime
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import DTYPE, Batch
from vfm_core.learning.streaming.learner import (
    CHECKPOINT_FORMATS,
    PARAMETER_UNITS,
    WellLearner,
    model_fixed_when_predicting,
    predicts_in_groups,
)
from vfm_core.learning.streaming.phases import phase_split, phase_split_numpy
from vfm_core.learning.streaming.protocol import Learner
from vfm_core.learning.streaming.samples import Row
from vfm_core.timeutil import from_ns

__all__ = [
    "Learner",
    "WellLearner",
    "predict_many",
    "learn_many",
    "model_fixed_when_predicting",
    "phase_split",
    "phase_split_numpy",
    "PARAMETER_UNITS",
    "CHECKPOINT_FORMATS",
]


if TYPE_CHECKING:  # a WellLearner keeps the Learner protocol (mypy checks the assignment)
    _KEEPS_PROTOCOL: type[Learner] = WellLearner

# -- many wells' predictions in one call ----------------------------------------------------------
Rates = dict[str, float | None]

#: a sample waiting for its group's model call: its place, learner, answer and row
_Waiting = tuple[int, "WellLearner", Rates, Row]


def predict_many(
    learners: Sequence[Any],
    inputs: Sequence[Sequence[float] | torch.Tensor],
    whens: Sequence[datetime | int | None] | None = None,
    *,
    return_exceptions: bool = False,
) -> list[Rates | BaseException]:
    """``[learner.predict(x, when) for ...]``, with the models of many wells run in one call.

    For a service that answers samples of many wells that arrive together. Each
    learner's side effects run as in :meth:`WellLearner.predict`, in the order given: the
    sample's features, then the retrains due (a ``pbl`` retrain due at a sample runs
    before its prediction). The learners whose methods have equal
    :meth:`~vfm_core.learning.LearningMethod.group_key` (the same model specification,
    and for ``bayes`` the same settings) then share one
    :meth:`~vfm_core.learning.LearningMethod.predict_group` call: each method stacks its
    wells' calls its own way. The answers equal the one-by-one answers (to rounding,
    1e-12 relative). A learner may come more than once (a well's consecutive samples):
    if its next sample may change its model (a scheduled retrain, see
    :func:`model_fixed_when_predicting`), what waits is predicted first. Anything else
    (a learner that does not predict in groups, :attr:`Learner.predicts_in_groups`: a
    field-wide well, a subclass with its own ``predict``) answers through its own
    ``predict``.

    ``inputs``: each sample's six inputs in file units; ``whens``: each sample's time (or
    None), a datetime or epoch ns (an int). With ``return_exceptions`` a learner that fails gets its exception in its place
    in the list (the others are still answered); otherwise the first error is raised.
    """
    n = len(learners)
    if len(inputs) != n or (whens is not None and len(whens) != n):
        raise ValueError(
            f"predict_many needs one input row and one time per learner; got {n} learners, "
            f"{len(inputs)} input rows and {'no' if whens is None else len(whens)} times."
        )
    results: list[Rates | BaseException | None] = [None] * n
    waiting: list[_Waiting] = []
    seen: set[int] = set()
    for i, learner in enumerate(learners):
        when = None if whens is None else whens[i]
        if id(learner) in seen and not model_fixed_when_predicting(learner):
            # its next sample may retrain it: answer what is waiting first
            _run_waiting(waiting, results)
            waiting, seen = [], set()
        try:
            if predicts_in_groups(learner):
                out, row = learner.prepare_sample(inputs[i], when)
                if row is None:
                    results[i] = out
                else:
                    waiting.append((i, learner, out, row))
                    seen.add(id(learner))
            else:  # its own predict: a datetime, as one-by-one callers give it
                results[i] = learner.predict(
                    inputs[i], when=from_ns(when) if type(when) is int else when
                )
        except Exception as exc:
            if not return_exceptions:
                raise
            results[i] = exc
    _run_waiting(waiting, results)
    return _finished(results, return_exceptions)


def _finished(results: list[Any], return_exceptions: bool) -> list[Any]:
    """The results, or the first error in them raised (without ``return_exceptions``)."""
    if not return_exceptions:
        for r in results:
            if isinstance(r, BaseException):
                raise r
    return results


def _by_key(items: Sequence[Any], key_of: Callable[[Any], Any]) -> dict[Any, list[int]]:
    """The positions of ``items`` grouped by ``key_of(item)`` (a method's group or learn
    key); an item whose key is None, or whose method fails to give one, is alone."""
    groups: dict[Any, list[int]] = {}
    for k, item in enumerate(items):
        try:
            key = key_of(item)
        except Exception:
            key = None
        groups.setdefault(("alone", k) if key is None else key, []).append(k)
    return groups


def _run_waiting(
    waiting: list[_Waiting],
    results: list[Rates | BaseException | None],
) -> None:
    """Predict the prepared samples, one call per group of methods with equal group keys."""
    groups = _by_key(waiting, lambda w: w[1].method.group_key())
    for key, members in groups.items():
        if len(members) > 1 and key[0] != "alone":
            try:
                _predict_group([waiting[k] for k in members], results)
                continue
            except Exception:  # noqa: S112 - the one-by-one path below says what failed
                pass
        for k in members:
            i, learner, out, row = waiting[k]
            try:
                forecast = learner.method.predict(learner.sample_batch(row))
                results[i] = learner.answer(out, forecast, row[0], 0)
            except Exception as exc:
                results[i] = exc


def _predict_group(members: list[_Waiting], results: list[Rates | BaseException | None]) -> None:
    """One :meth:`~vfm_core.learning.LearningMethod.predict_group` call for the samples of
    one group; each learner's answer filled in."""
    first = members[0][1]
    k = len(members)
    # as the one-sample batches of WellLearner.sample_batch, one row per well
    xs, ts, extras = zip(*[m[3] for m in members], strict=True)
    x_np = np.array(xs, dtype=np.float64)
    batch = Batch(
        [m[1].well for m in members],
        torch.from_numpy(x_np).reshape(k, 1, 6).to(DTYPE),
        torch.zeros(k, 1, dtype=DTYPE),
        torch.ones(k, 1, dtype=torch.bool),
        torch.from_numpy(np.array(ts, dtype=np.int64)).reshape(k, 1),
        torch.zeros(k, 1, dtype=torch.int64),
        torch.ones(k, 1, dtype=torch.bool),
        torch.from_numpy(np.array(extras, dtype=np.float64)).reshape(k, 1, -1).to(DTYPE),
        tuple(first.model.extra_columns),
    )
    with torch.no_grad():
        forecast = type(first.method).predict_group([m[1].method for m in members], batch)
    q_total = forecast.mean[:, 0].detach().numpy()
    columns = {"q_total": q_total.tolist()}
    columns.update({name: v.tolist() for name, v in phase_split_numpy(q_total, x_np).items()})
    if forecast.std is not None:
        columns["q_total_std"] = forecast.std[:, 0].tolist()
    if forecast.p05 is not None and forecast.p95 is not None:
        columns["q_total_p05"] = forecast.p05[:, 0].tolist()
        columns["q_total_p95"] = forecast.p95[:, 0].tolist()
    names = list(columns)
    for (i, _, out, _), values in zip(members, zip(*columns.values(), strict=True), strict=True):
        out.update(zip(names, values, strict=True))
        results[i] = out


# -- many wells' updates in one call --------------------------------------------------------------
#: a measurement taken and waiting for its group's update: its place, learner, the
#: measurement as a one-well batch, its time, and whether a retrain already changed the model
_Taken = tuple[int, "WellLearner", Batch, pd.Timestamp, bool]


def learn_many(
    learners: Sequence[Any],
    inputs: Sequence[Sequence[float] | torch.Tensor],
    q_totals: Sequence[float],
    whens: Sequence[datetime],
    sources: Sequence[str] | None = None,
    *,
    return_exceptions: bool = False,
) -> list[bool | BaseException]:
    """``[learner.learn(x, q, when, source) for ...]``, with many wells' updates in one call.

    For a service that learns from measurements of many wells that arrive together. Each
    learner's side effects run as in :meth:`WellLearner.learn`, in the order given (the
    retrains due, the features, the memory); then the learners whose methods have equal
    :meth:`~vfm_core.learning.LearningMethod.learn_key` learn in one
    :meth:`~vfm_core.learning.LearningMethod.learn_group` call, each method stacking its
    wells' updates its own way (``ol``: the E optimiser steps with the wells' optimiser
    states stacked; ``bayes``: the filter's Kalman step with the wells' filter states
    stacked, as the study updates a field's wells in one call).

    Each learner's parameters and method state are then its own again, so its checkpoint
    and later one-by-one calls are what learning one by one leaves: the parameters,
    optimiser and filter states and later predictions equal it to rounding (1e-12
    relative; a filter's covariance to 1e-12 of its largest entry). A learner that comes
    twice waits for its first measurement to be learned. Anything else (``pbl``, whose
    learn only stores the measurement; a subclass with its own ``learn``; a model that
    cannot be stacked) learns through its own ``learn``, in order.

    ``inputs``: each measurement's six inputs in file units; ``q_totals``: the measured
    total rates, Sm3/h; ``whens``: their times; ``sources``: ``mpfm`` (the default) or
    ``well_test`` each. Returns, per learner, True when its model changed. With
    ``return_exceptions`` a learner that fails gets its exception in its place (the
    others still learn); otherwise the first error is raised once every measurement
    taken before it has been learned.
    """
    n = len(learners)
    if (
        len(inputs) != n
        or len(q_totals) != n
        or len(whens) != n
        or (sources is not None and len(sources) != n)
    ):
        raise ValueError(
            f"learn_many needs one input row, rate and time (and source, if given) per "
            f"learner; got {n} learners, {len(inputs)} input rows, {len(q_totals)} rates, "
            f"{len(whens)} times and {'no' if sources is None else len(sources)} sources."
        )
    results: list[bool | BaseException | None] = [None] * n
    waiting: list[_Taken] = []
    seen: set[int] = set()
    for i, learner in enumerate(learners):
        source = "mpfm" if sources is None else sources[i]
        if id(learner) in seen:  # its earlier measurement is learned first
            _learn_waiting(waiting, results)
            waiting, seen = [], set()
        try:
            if _learn_batchable(learner):
                ts, changed, batch = learner.take_measurement(
                    inputs[i], q_totals[i], whens[i], source
                )
                waiting.append((i, learner, batch, ts, changed))
                seen.add(id(learner))
            else:
                results[i] = learner.learn(inputs[i], q_totals[i], whens[i], source)
        except Exception as exc:
            if not return_exceptions:
                _learn_waiting(waiting, results)
                raise
            results[i] = exc
    _learn_waiting(waiting, results)
    return _finished(results, return_exceptions)


def _learn_batchable(learner: Any) -> bool:
    """True when ``learner`` says its learn can be split around one update shared with
    others (:attr:`Learner.learns_in_groups`: a :class:`WellLearner` learning with
    :meth:`WellLearner.learn` itself, whose method learns in groups, on a gradient model);
    anything without the capability learns through its own ``learn``."""
    return bool(getattr(learner, "learns_in_groups", False))


def _learn_waiting(waiting: list[_Taken], results: list[bool | BaseException | None]) -> None:
    """Learn the taken measurements, one group call per group of methods with equal keys."""
    groups = _by_key(waiting, lambda w: w[1].method.learn_key())
    for key, members in groups.items():
        if len(members) > 1 and key[0] != "alone":
            try:
                rest = _learn_group([waiting[k] for k in members], key, results)
            except Exception:  # the one-by-one path below says what failed
                rest = [waiting[k] for k in members]
        else:
            rest = [waiting[k] for k in members]
        for i, learner, batch, ts, changed in rest:
            try:
                results[i] = learner.learn_taken(batch, ts, changed)
            except Exception as exc:
                results[i] = exc


def _learn_group(
    members: list[_Taken], key: Any, results: list[bool | BaseException | None]
) -> list[_Taken]:
    """One :meth:`~vfm_core.learning.LearningMethod.learn_group` call for one group's
    measurements; a new version for each learner whose model changed. Returns the members
    the method left to learn one by one."""
    methods = [m[1].method for m in members]
    outcome = type(methods[0]).learn_group(
        methods, [m[2] for m in members], [m[1].memory for m in members]
    )
    rest: list[_Taken] = []
    for member, moved in zip(members, outcome, strict=True):
        i, learner, _, ts, was = member
        if moved is None:
            rest.append(member)
            continue
        if moved:
            learner.new_version(ts.to_pydatetime(warn=False))
        results[i] = was or moved
    return rest
