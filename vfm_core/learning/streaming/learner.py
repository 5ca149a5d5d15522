"""One well's model and learning method, fed one sample at a time: the core of the service.

See :class:`WellLearner`; :mod:`vfm_core.learning.streaming` describes the package.
"""

from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import replace
from datetime import datetime
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.features import FeatureTracker
from vfm_core.learning import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    Forecast,
    LearningMethod,
    OnlineSettings,
    TrainSettings,
    WellMemory,
    parse_method,
)
from vfm_core.learning.streaming.phases import phase_split
from vfm_core.learning.streaming.samples import Row, epoch_ns, history_rows, one_sample, six_inputs
from vfm_core.models import MODELS, ChokeModel, make_model
from vfm_core.timeutil import utc_timestamp

__all__ = [
    "WellLearner",
    "PARAMETER_UNITS",
    "CHECKPOINT_FORMATS",
    "model_fixed_when_predicting",
    "predicts_in_groups",
]

PARAMETER_UNITS: dict[str, str] = {name: p.unit for name, p in ph.PRIORS.items()} | {"a_max": "m2"}
#: the checkpoint formats :meth:`WellLearner.restore` reads (the first writes today's)
CHECKPOINT_FORMATS = ("vfm-well-learner/3", "vfm-well-learner/2", "vfm-well-learner/1")
#: the keys of :meth:`WellLearner.predict`'s answer, in order
_ANSWER_KEYS = ("q_total", "q_gas", "q_oil", "q_water", "q_total_std", "q_total_p05", "q_total_p95")


class WellLearner:
    """A per-well model with its learning method, for streaming use."""

    def __init__(
        self,
        well: str,
        model: str = "mm",
        method: str = "ol",
        *,
        train: TrainSettings | None = None,
        online: OnlineSettings | None = None,
        model_kwargs: dict[str, Any] | None = None,
        seed: int = 0,
        effects: Sequence[Any] = (),
        remember_max: int | None = None,
    ) -> None:
        if model not in MODELS:
            raise ConfigError(f"Unknown model '{model}'; choose one of {', '.join(MODELS)}.")
        if MODELS[model].shared:
            raise ConfigError(
                f"Model '{model}' shares parameters across the whole field, so a one-well learner "
                "cannot hold it; use vfm_core.learning.field.FieldLearner (the service does so when "
                "model.name is mtl), or choose a per-well model."
            )
        self.well = well
        self.model_name = model
        self.train = train or DEFAULT_TRAIN[model]
        self.online = online or DEFAULT_ONLINE[model]
        self.model_kwargs = dict(model_kwargs or {})
        self.seed = seed
        self.model: ChokeModel = make_model(
            model, [well], seed=seed, effects=list(effects), **self.model_kwargs
        )
        #: the effects as texts that rebuild them (registry names, settings, module:Class)
        self.effects: list[str] = list(self.model.hyper.get("effects", []))
        unknown = [c for c in self.model.extra_columns if c not in FeatureTracker.names]
        if unknown:
            raise ConfigError(
                f"The model {self.model.name} needs the feature(s) {unknown}, which the streaming "
                f"learner cannot compute sample by sample (it keeps {', '.join(FeatureTracker.names)}); "
                "use the effect with `vfm evaluate` or `vfm diagnose`."
            )
        meth = parse_method(method)
        if not meth.streaming:
            raise ConfigError(
                f"The learning method '{meth.text}' cannot run in the streaming learner."
            )
        self.method: LearningMethod = meth.bind(self.model, train=self.train, online=self.online)
        self._cols = [FeatureTracker.names.index(c) for c in self.model.extra_columns]
        self.features = FeatureTracker()
        #: every measurement learned from (inputs, rate, time, source, features)
        #: (``remember_max``: at most that many, the latest; see WellMemory.set_max_rows)
        self.memory = WellMemory(
            well, FeatureTracker.names, self.model.extra_columns, max_rows=remember_max
        )
        self.version = 0
        self.n_updates = 0
        self.last_update: datetime | None = None

    @property
    def remembered(self) -> int:
        """How many measurements the learner keeps for retrains and model changes."""
        return len(self.memory)

    @property
    def name(self) -> str:
        """The model's full name, e.g. ``mm`` or ``mm+erosion``."""
        return str(self.model.name)

    @property
    def ready(self) -> bool:
        """True once the model has seen enough data to predict (priors alone give no scale)."""
        # asked on every sample: read the flag once per change of its tensor (an in-place
        # change bumps the tensor's version; a new model brings a new tensor)
        model = self.model
        flag = model._buffers.get("ready")  # a buffer: no Module.__getattr__ on every sample
        if flag is None:
            flag = model.ready
        cached = self.__dict__.get("_ready")
        if cached is not None and cached[0] is flag and cached[1] == flag._version:
            return bool(cached[2])
        value = bool(flag[0])
        self.__dict__["_ready"] = (flag, flag._version, value)
        return value

    # -- what it can do (see vfm_core.learning.streaming.protocol.Learner) ---------------------------
    #: its model is its own: a step for this well changes no other well's predictions
    shares_model = False
    #: its checkpoint holds this well alone and restores it alone (:meth:`restore`)
    checkpoint_group = None

    @property
    def predicts_in_groups(self) -> bool:
        """True while :meth:`predict` is the one defined here (not a subclass's own, nor a
        replacement): it is then the steps :meth:`prepare_sample`, one model call
        (shareable with other learners) and :meth:`answer`."""
        return type(self).predict is _WELL_PREDICT

    @property
    def learns_in_groups(self) -> bool:
        """True when :meth:`learn` is the one defined here (not a subclass's own, nor a
        replacement), the method learns in groups (its class has a ``learn_key``) and the
        model takes gradient steps: the update of :meth:`take_measurement`'s batch can then
        be stacked with other wells'."""
        return (
            type(self).learn is _WELL_LEARN
            and type(self.method).learn_key is not LearningMethod.learn_key
            and not self.model.gradient_free
        )

    def renumber(self, at_least: int) -> None:
        """Version ``at_least`` if the model's own is lower (it replaces a model of that
        version less one, and versions keep rising)."""
        self.version = max(self.version, at_least)

    def remember_at_most(self, rows: int | None) -> None:
        """Keep at most ``rows`` measurements, the latest (None: all); see
        :meth:`vfm_core.learning.WellMemory.set_max_rows`."""
        self.memory.set_max_rows(rows)

    def deferred_note(self) -> str:
        """A measurement the model did not learn from at once waits for its next retrain."""
        return (
            f"Stored; the model keeps it for its next periodic retrain (method {self.method.text})."
        )

    # -- history --------------------------------------------------------------------------
    def fit_history(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        time_ns: torch.Tensor,
        *,
        well_test: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
        tracker: FeatureTracker | None = None,
    ) -> None:
        """Initial MAP fit on a well's history: inputs [N, 6], rates [N] Sm3/h, times [N] ns.

        ``well_test`` [N] marks well tests (default: none); ``features`` [N, k] are the
        standard features of :class:`vfm_core.features.FeatureTracker` at those rows and
        ``tracker`` the tracker after them (both computed from the rows when not given).
        """
        if int(x.shape[0]) == 0:
            return
        x, y, t, w, e, tracker = history_rows(x, y, time_ns, well_test, features, tracker)
        history = WellMemory(self.well, FeatureTracker.names, self.model.extra_columns)
        history.append(x, y, t, w, e)
        self.method.fit(history.rows())
        self._remember_history(x, y, t, w, e, tracker, None)

    def adopt_fit(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        time_ns: torch.Tensor,
        iterations: torch.Tensor,
        first_retrain_base: datetime | None = None,
        *,
        well_test: torch.Tensor | None = None,
        features: torch.Tensor | None = None,
        tracker: FeatureTracker | None = None,
    ) -> None:
        """Take on an initial fit done elsewhere (e.g. one batched fit of the whole field).

        The model's parameters must already hold the fit; this records the history it was
        fitted on (with ``well_test``, ``features`` and ``tracker`` as in
        :meth:`fit_history`), the early-stopped iteration count for later retrains, and
        the calendar of scheduled retrains: from ``first_retrain_base`` (e.g. the split, as
        ``vfm evaluate`` counts) or from the last history row.
        """
        x, y, t, w, e, tracker = history_rows(x, y, time_ns, well_test, features, tracker)
        history = WellMemory(self.well, FeatureTracker.names, self.model.extra_columns)
        history.append(x, y, t, w, e)
        self.method.adopt(history.rows(), iterations)
        self._remember_history(x, y, t, w, e, tracker, first_retrain_base)

    def _remember_history(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        t: torch.Tensor,
        w: torch.Tensor,
        e: torch.Tensor,
        tracker: FeatureTracker,
        base: datetime | None,
    ) -> None:
        self.memory.append(x, y, t, w, e)
        self.features = tracker
        last = pd.Timestamp(int(t.max()), tz="UTC")
        self.new_version(last.to_pydatetime())
        self.method.start(int((last if base is None else utc_timestamp(base)).value))

    def new_version(self, when: datetime) -> None:
        """Count a change of the model (a new version), made at ``when``."""
        self.version += 1
        self.n_updates += 1
        self.last_update = when

    def _retrains_due(self, now: pd.Timestamp | int) -> bool:
        """Run the method's scheduled retrains due by ``now`` (or epoch ns); one version per
        retrain."""
        before = self.method.n_retrains
        now_ns = now if isinstance(now, int) else now.value
        self.method.retrain_due(self.memory, torch.tensor([now_ns], dtype=torch.int64))
        new = self.method.n_retrains - before
        done = self.method.retrains[-new:] if new > 0 else []
        for until in done:
            self.new_version(pd.Timestamp(until, tz="UTC").to_pydatetime(warn=False))
        return bool(done)

    # -- streaming ------------------------------------------------------------------------
    def predict(
        self, inputs: Sequence[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        """Rates (Sm3/h) for one sample's inputs; all None until the model is ready.

        ``q_total`` and its phase split ``q_gas``, ``q_oil``, ``q_water``; with a method that
        gives intervals also ``q_total_std`` and the central 90 % interval ``q_total_p05``,
        ``q_total_p95`` (else None). A sample time ``when`` past the method's next scheduled
        retrain retrains first (on everything learned before that time), so the calendar of
        retrains matches ``vfm evaluate``.
        """
        out, row = self.prepare_sample(inputs, when)
        if row is None:
            return out
        return self.answer(out, self.method.predict(self.sample_batch(row)), row[0], 0)

    def prepare_sample(
        self, inputs: Sequence[float] | torch.Tensor, when: datetime | int | None
    ) -> tuple[dict[str, float | None], Row | None]:
        """The side effects of :meth:`predict` before the model runs, in its order: the
        sample's features, then the retrains due. Returns the answer to fill and the sample
        as plain numbers (None while the model is not ready): inputs, time (ns, 0 for
        none) and the model's feature columns."""
        x = six_inputs(inputs)
        ns = None if when is None else epoch_ns(when)
        # the sample's features (a sample without a time sits at the latest one)
        at = self.features.last_ns if ns is None else ns
        feats = (
            [0.0] * len(FeatureTracker.names)
            if at is None
            else self.features.advance(int(at), x[4], x[5])
        )
        if ns is not None and type(self.method).retrain_due is not LearningMethod.retrain_due:
            self._retrains_due(ns)  # (the base method never retrains: nothing to run)
        out: dict[str, float | None] = dict.fromkeys(_ANSWER_KEYS)
        if not self.ready:
            return out, None
        # the best estimate of the true rate: the sample as if a well test measured it
        return out, (x, 0 if at is None else int(at), [feats[c] for c in self._cols])

    def sample_batch(self, row: Row) -> Batch:
        """One prepared sample as a one-well batch (as a well test, see :meth:`predict`)."""
        x, at, extra = row
        return one_sample(
            torch.tensor(x, dtype=DTYPE),
            0.0,
            at,
            True,
            torch.tensor(extra, dtype=DTYPE),
            tuple(self.model.extra_columns),
        )

    @staticmethod
    def answer(
        out: dict[str, float | None], forecast: Forecast, x: list[float], row: int
    ) -> dict[str, float | None]:
        """Fill ``out`` from row ``row`` of ``forecast`` ([W, 1]) for the sample's inputs ``x``."""
        q = forecast.mean[row : row + 1]
        xt = torch.tensor(x, dtype=DTYPE).reshape(1, 1, 6)
        out["q_total"] = float(q[0, 0])
        out.update({k: float(v[0, 0]) for k, v in phase_split(q, xt).items()})
        if forecast.std is not None:
            out["q_total_std"] = float(forecast.std[row, 0])
        if forecast.p05 is not None and forecast.p95 is not None:
            out["q_total_p05"] = float(forecast.p05[row, 0])
            out["q_total_p95"] = float(forecast.p95[row, 0])
        return out

    def predict_block(self, inputs: np.ndarray, times_ns: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`predict` for a block of one well's samples in time order, in one model call.

        ``inputs`` [N, 6] in file units, ``times_ns`` [N] epoch ns. For a learner whose
        model cannot change while predicting (:func:`model_fixed_when_predicting`: ``ol``,
        ``bayes``) and that is ready; the answers equal N calls of :meth:`predict` (to
        rounding) and so does the state after (the features; left as they were when the
        model call fails). Returns each of
        ``q_total``, ``q_gas``, ``q_oil``, ``q_water`` as an array [N] (Sm3/h), and with a
        method that gives intervals also ``q_total_std``, ``q_total_p05``, ``q_total_p95``.
        """
        t = np.asarray(times_ns, dtype=np.int64).reshape(-1)
        if not model_fixed_when_predicting(self, int(t[-1]) if len(t) else None) or not self.ready:
            raise ValueError(
                f"predict_block needs a ready model that predicting cannot change; {self.well} "
                f"({self.name}) is {'not ready' if not self.ready else 'retrained on a schedule'}."
            )
        x = np.asarray(inputs, dtype=float).reshape(-1, 6)
        n = len(t)
        if len(x) != n:
            raise ValueError(f"predict_block needs one time per input row; got {len(x)} and {n}.")
        tracker = self.features
        before = (tracker.first_ns, tracker.last_ns, tracker.cumulative, tracker.scale)
        feats = tracker.advance_many(t, x[:, 4], x[:, 5])
        try:
            return self._block_answer(x, t, feats)
        except BaseException:  # nothing happened: the features are as they were
            tracker.first_ns, tracker.last_ns, tracker.cumulative, tracker.scale = before
            raise

    def _block_answer(
        self, x: np.ndarray, t: np.ndarray, feats: np.ndarray
    ) -> dict[str, np.ndarray]:
        """The model's answers for a block's rows (see :meth:`predict_block`)."""
        n = len(t)
        batch = Batch(
            ["well"],
            torch.tensor(x, dtype=DTYPE).reshape(1, n, 6),
            torch.zeros(1, n, dtype=DTYPE),
            torch.ones(1, n, dtype=torch.bool),
            torch.tensor(t).reshape(1, n),
            torch.zeros(1, n, dtype=torch.int64),
            torch.ones(1, n, dtype=torch.bool),  # as a well test would measure it (predict)
            torch.tensor(feats[:, self._cols], dtype=DTYPE).reshape(1, n, -1),
            tuple(self.model.extra_columns),
        )
        with torch.no_grad():
            forecast = self.method.predict(batch)
        out = {"q_total": forecast.mean[0].numpy()}
        out.update({k: v[0].numpy() for k, v in phase_split(forecast.mean, batch.x).items()})
        if forecast.std is not None:
            out["q_total_std"] = forecast.std[0].numpy()
        if forecast.p05 is not None and forecast.p95 is not None:
            out["q_total_p05"] = forecast.p05[0].numpy()
            out["q_total_p95"] = forecast.p95[0].numpy()
        return out

    def learn(
        self,
        inputs: Sequence[float] | torch.Tensor,
        q_total: float,
        when: datetime,
        source: str = "mpfm",
    ) -> bool:
        """Learn from one measured rate (Sm3/h) paired with the inputs at its time.

        ``source`` is ``mpfm`` or ``well_test`` (each has its own noise for methods that
        weigh them, and effects such as a meter bias tell them apart). Scheduled retrains
        that are due run first; the method then learns now or keeps the measurement for
        its next retrain. Returns True when the model changed.
        """
        ts, changed, batch = self.take_measurement(inputs, q_total, when, source)
        return self.learn_taken(batch, ts, changed)

    def take_measurement(
        self,
        inputs: Sequence[float] | torch.Tensor,
        q_total: float,
        when: datetime,
        source: str,
    ) -> tuple[pd.Timestamp, bool, Batch]:
        """The side effects of :meth:`learn` before the method learns, in its order: the
        retrains due, the features, the memory. Returns the measurement's time, whether a
        retrain changed the model, and the measurement as a one-well batch."""
        ts = utc_timestamp(when)
        changed = self._retrains_due(ts)
        x = torch.as_tensor(inputs, dtype=DTYPE).reshape(1, 6)
        feats = torch.tensor(
            [self.features.advance(ts.value, float(x[0, 4]), float(x[0, 5]))], dtype=DTYPE
        )
        self.features.measured(ts.value, float(q_total))
        well_test = source == "well_test"
        self.memory.append(
            x,
            torch.tensor([float(q_total)], dtype=DTYPE),
            torch.tensor([ts.value], dtype=torch.int64),
            torch.tensor([well_test]),
            feats,
        )
        batch = one_sample(
            x,
            float(q_total),
            ts.value,
            well_test,
            feats[0, self._cols],
            tuple(self.model.extra_columns),
        )
        return ts, changed, batch

    def learn_taken(self, batch: Batch, ts: pd.Timestamp, changed: bool) -> bool:
        """The rest of :meth:`learn`: the method learns from the measurement taken by
        :meth:`take_measurement`; a new version if the model changed."""
        if bool(self.method.on_measurement(batch, self.memory).any()):
            self.new_version(ts.to_pydatetime(warn=False))
            changed = True
        return changed

    def retrain(self, now: datetime | pd.Timestamp) -> None:
        """Retrain now on everything learned up to ``now`` (e.g. after a confirmed drift);
        scheduled retrains then count their period from ``now``."""
        ts = utc_timestamp(now)
        self.method.retrain(self.memory, int(ts.value) + 1)
        self.method.start(int(ts.value))
        self.new_version(ts.to_pydatetime(warn=False))

    # -- state ----------------------------------------------------------------------------
    def physical_parameters(self) -> dict[str, dict[str, Any]]:
        """Named physical parameters (effects' as ``effect.name``): ``value`` (SI), ``unit``,
        ``std`` (the learning method's posterior standard deviation; None for a method that
        keeps no uncertainty), the bounds ``low`` and ``high`` learning may not cross (None
        for a set quantity such as ``a_max``), and ``at_bound``: True when the value sits
        within a thousandth of the range of a bound that is not also the prior's mean (the
        data push it beyond what physics allows: often a sign of a missing effect), and
        ``fixed``: True for an effect's parameter the model's specification sets
        (``valve_equal_percentage:weight=1.006``, as the diagnosis identifies it on a hybrid's
        core; :func:`vfm_core.effects.fixed_effect`): nothing learns it, so its ``std`` is
        None, not the pinning prior's 1e-9."""
        priors = dict(ph.PRIORS)
        fixed: set[str] = set()
        for e in getattr(self.model, "effects", []):
            priors.update({f"{e.name}.{k}": pr for k, pr in e.parameters.items()})
            fixed.update(f"{e.name}.{k}" for k in getattr(e, "fixed_values", {}))
        sd = self.method.parameter_sd()
        out: dict[str, dict[str, Any]] = {}
        for name, v in self.model.physical_parameters().items():
            value = float(v[0])
            prior = priors.get(name)
            std = None if name in fixed else sd.get(name)
            entry: dict[str, Any] = {
                "value": value,
                "unit": prior.unit if prior is not None else PARAMETER_UNITS.get(name, ""),
                "std": float(std[0]) if std is not None else None,
                "low": prior.low if prior is not None else None,
                "high": prior.high if prior is not None else None,
                "at_bound": False,
                "fixed": name in fixed,
            }
            if prior is not None:
                # a bound that is also the prior's mean is the effect switched off, not a warning
                tol = 1e-3 * (prior.high - prior.low)
                low = prior.low < prior.mean and value <= prior.low + tol
                high = prior.high > prior.mean and value >= prior.high - tol
                entry["at_bound"] = bool(low or high)
            out[name] = entry
        return out

    # -- another model on the same history ----------------------------------------------------
    def refit_as(
        self,
        model: str | None = None,
        effects: Sequence[str] | None = None,
        method: str | None = None,
        *,
        holdout: float = 0.2,
        time_budget_s: float | None = None,
    ) -> tuple[WellLearner, dict[str, Any]]:
        """A new learner with another model (and effects) fitted on everything this one remembers.

        Before the final fit on all of it, both the current specification and the new one
        are fitted on the oldest ``1 - holdout`` of the history (by time) and scored on the
        rest (MAPE, %), each learning with its own method over the rest as the service
        runs it (:meth:`_replay`): the check scores what the trial will (fitted once, a
        model whose misfit the learner absorbs looked worse than it runs, and a change of
        the method alone was not judged). The new learner carries the feature state on,
        and its version is this one's plus one.

        ``mm`` (with or without effects) is fitted to convergence here: its priors are its
        regulariser, and early stopping on the latest fifth of a drifting history stops
        before a trend such as wear is learned (measured: wear rate 0.0015 instead of 0.33,
        held-out MAPE 13.6 % instead of 2.1 %, on a simulated eroding well). Models with a
        network (``hem``, ``ham``, ...) keep early stopping. ``time_budget_s`` bounds each
        of the three fits' wall-clock time (see ``TrainSettings.time_budget_s``) and stays
        the new learner's budget for its retrains.
        """
        model = model or self.model_name
        effects = list(self.effects if effects is None else effects)
        method = method or self.method.text
        t_all = self.memory.t
        n = int(t_all.shape[0])
        if n < 10:
            raise ConfigError(
                f"Well {self.well} has {n} stored measurement(s); at least 10 are needed to fit a new model."
            )
        same_base = model == self.model_name

        def budgeted(train: TrainSettings) -> TrainSettings:
            if time_budget_s is None:
                return train
            return replace(train, time_budget_s=time_budget_s)

        new = WellLearner(
            self.well,
            model,
            method,
            train=budgeted(self.train if same_base else DEFAULT_TRAIN[model]),
            online=self.online if same_base else None,
            model_kwargs=self.model_kwargs if same_base else None,
            seed=self.seed,
            effects=effects,
        )
        order = torch.argsort(t_all, stable=True)
        if new.method.window is not None:  # a method with a window: fit on the window only
            start = int(t_all.max()) - int(new.method.window.value)
            order = order[t_all[order] >= start]
            n = int(order.numel())
        cut = order[: max(int(round(n * (1.0 - holdout))), 1)]
        test = order[len(cut) :]
        scores: dict[str, Any] = {"holdout_rows": int(len(test)), "unit": "%"}
        if len(test) >= 5:
            t0 = pd.Timestamp(int(t_all[test].min()), tz="UTC")
            scores["holdout_from"] = t0.isoformat()
            scores["protocol"] = "replayed"
            for key, spec_model, spec_effects, like in (
                ("before", self.model_name, self.effects, self),
                ("after", model, effects, new),
            ):
                scores[key] = self._holdout_mape(
                    spec_model, spec_effects, like, cut, test, budgeted(like.train)
                )
        new._fit_rows(self, order, converge=model == "mm")
        new.features = FeatureTracker.from_state(self.features.state())
        new.version = self.version + 1
        new.n_updates = self.n_updates + 1
        new.last_update = self.last_update
        if self.last_update is not None:
            new.method.start(int(utc_timestamp(self.last_update).value))
        return new, scores

    def _holdout_mape(
        self,
        model: str,
        effects: Sequence[str],
        like: WellLearner,
        cut: torch.Tensor,
        test: torch.Tensor,
        train: TrainSettings,
    ) -> float:
        """MAPE (%) on the ``test`` rows of this learner's memory of ``model`` with
        ``effects`` and ``like``'s method, fitted on the ``cut`` rows (with ``like``'s
        settings; ``mm`` to convergence, as :meth:`refit_as` fits it), then replayed over
        the ``test`` rows in time order (:meth:`_replay`)."""
        trial = WellLearner(
            self.well,
            model,
            like.method.text,
            train=train,
            online=like.online,
            model_kwargs=like.model_kwargs,
            seed=self.seed,
            effects=effects,
        )
        trial._fit_rows(self, cut, converge=model == "mm")
        held = WellMemory(self.well, FeatureTracker.names, trial.model.extra_columns)
        held.copy_from(self.memory, test)
        q = trial._replay(held)
        y = held.y
        ok = torch.abs(y) > 1e-9  # a zero rate has no relative error
        return float((torch.abs(q - y)[ok] / torch.abs(y[ok])).mean() * 100.0)

    def _replay(self, held: WellMemory) -> torch.Tensor:
        """Predict each of ``held``'s rows (time order) before learning it, as the service
        runs the method: the retrains due by the row's time first, then the prediction, then
        the row joins the memory and the method learns from it. The predicted rates (Sm3/h)."""
        x, y, t, w, e = held.x, held.y, held.t, held.well_test, held.features
        n = int(y.shape[0])
        out = torch.empty(n, dtype=DTYPE)
        if n == 0:
            return out
        if len(self.memory):
            self.method.start(int(self.memory.t.max()))
        scheduled = type(self.method).retrain_due is not LearningMethod.retrain_due
        for i in range(n):
            if scheduled:
                self._retrains_due(int(t[i]))
            one = held.rows(torch.tensor([i]))
            out[i] = self.method.predict(one).mean[0, 0]
            self.memory.append(x[i : i + 1], y[i : i + 1], t[i : i + 1], w[i : i + 1], e[i : i + 1])
            self.method.on_measurement(one, self.memory)
        return out

    def _fit_rows(self, source: WellLearner, rows: torch.Tensor, converge: bool = False) -> None:
        """Fit this (fresh) learner on rows of another learner's memory and remember them
        (``converge``: run ``max_iter`` iterations, no early stopping)."""
        self.memory.copy_from(source.memory, rows)
        self.method.fit(self.memory.rows(), converge=converge)

    # -- checkpoints ----------------------------------------------------------------------------
    def checkpoint(self) -> bytes:
        """Everything needed to resume, as bytes (tensors and plain values, no pickle)."""
        payload = {
            "format": CHECKPOINT_FORMATS[0],
            "well": self.well,
            "model": self.model_name,
            "effects": json.dumps(self.effects),
            "features": json.dumps(self.features.state()),
            "method": self.method.text,
            "method_state": self.method.state_dict(),
            "train": json.dumps(self.train.__dict__),
            "online": json.dumps(self.online.__dict__),
            "model_kwargs": json.dumps(self.model_kwargs),
            "seed": self.seed,
            "state": self.model.state_dict(),
            "version": self.version,
            "n_updates": self.n_updates,
            "last_update": self.last_update.isoformat() if self.last_update else "",
            "memory": self.memory.state(),
        }
        buf = io.BytesIO()
        torch.save(payload, buf)
        return buf.getvalue()

    @classmethod
    def restore(cls, blob: bytes) -> WellLearner:
        """Rebuild a learner from :meth:`checkpoint` bytes (``weights_only``: never runs code).

        Reads today's format and the two before it (format 2 had no method state of its own:
        its optimiser, retrain time and iteration counts are taken over; format 1 kept no
        measurement sources or features: they are rebuilt from the remembered rows)."""
        try:
            p = torch.load(io.BytesIO(blob), weights_only=True)
        except Exception as exc:
            raise ConfigError(f"The checkpoint cannot be read: {exc}") from None
        if not isinstance(p, dict) or p.get("format") not in CHECKPOINT_FORMATS:
            raise ConfigError(
                f"The checkpoint is not a VFM well-learner checkpoint ({' or '.join(CHECKPOINT_FORMATS)})."
            )
        learner = cls(
            p["well"],
            p["model"],
            p["method"],
            train=replace(TrainSettings(), **json.loads(p["train"])),
            online=replace(OnlineSettings(), **json.loads(p["online"])),
            model_kwargs=json.loads(p["model_kwargs"]),
            seed=int(p["seed"]),
            effects=json.loads(p.get("effects", "[]")),
        )
        learner.model.load_state_dict(p["state"])
        learner.version = int(p["version"])
        learner.n_updates = int(p["n_updates"])
        learner.last_update = datetime.fromisoformat(p["last_update"]) if p["last_update"] else None
        if p["format"] == CHECKPOINT_FORMATS[0]:
            learner.method.load_state_dict(p["method_state"])
            learner.memory.load(p["memory"])
            learner.features = FeatureTracker.from_state(json.loads(p["features"]))
            return learner
        # formats 1 and 2: the method's state was kept in fields of the learner
        nxt = p.get("next_retrain") or ""
        learner.method.load_state_dict(
            {
                "iterations": p["iterations"],
                "optimizer": p.get("optimizer") or {},
                "next_due": int(pd.Timestamp(nxt).value) if nxt else None,
            }
        )
        if "w" in p:  # format 2
            learner.memory.load({"x": p["x"], "y": p["y"], "t": p["t"], "w": p["w"], "e": p["e"]})
            learner.features = FeatureTracker.from_state(json.loads(p["features"]))
        else:  # format 1: no sources or features were kept; rebuild the features
            x, y, t, w, e, tracker = history_rows(p["x"], p["y"], p["t"], None, None, None)
            learner.memory.load({"x": x, "y": y, "t": t, "w": w, "e": e})
            learner.features = tracker
        return learner


#: :meth:`WellLearner.predict` and :meth:`WellLearner.learn` as defined here (a subclass,
#: or a replacement patched onto the class, predicts or learns its own way)
_WELL_PREDICT = WellLearner.predict
_WELL_LEARN = WellLearner.learn


def model_fixed_when_predicting(learner: Any, until_ns: int | None = None) -> bool:
    """True when predicting cannot change ``learner``'s model: a learner that predicts in
    groups (:func:`predicts_in_groups`) whose method has no scheduled retrains (``ol``,
    ``bayes`` on most models), or, for samples up to ``until_ns`` (epoch ns; a block's
    last), none due by then (a retrain runs at the first sample at or after its due time).
    Several samples of such a well can then be predicted in one call
    (:func:`predict_many`); with ``pbl`` a sample may first retrain the model, so each
    sample waits for the one before."""
    if not predicts_in_groups(learner):
        return False
    if type(learner.method).retrain_due is LearningMethod.retrain_due:
        return True
    due = learner.method.next_due()
    return due is None or (until_ns is not None and int(until_ns) < int(due))


def predicts_in_groups(learner: Any) -> bool:
    """True when ``learner`` says its predict can be split around one model call
    (:attr:`vfm_core.learning.streaming.Learner.predicts_in_groups`: a :class:`WellLearner` that
    predicts with :meth:`WellLearner.predict` itself); anything without the capability
    answers through its own ``predict``."""
    return bool(getattr(learner, "predicts_in_groups", False))
