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
"""

from __future__ import annotations

import copy
import functools
import io
import json
import threading
from collections.abc import Sequence
from dataclasses import replace
from datetime import datetime
from typing import Any

import numpy as np
import pandas as pd
import torch
import torch.optim.optimizer as _torch_optimizer

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.features import FeatureTracker
from vfm_core.learning import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    BayesianFilter,
    Forecast,
    LearningMethod,
    OnlineLearning,
    OnlineSettings,
    TrainSettings,
    WellMemory,
    parse_method,
)
from vfm_core.learning.kernels import (
    fit_parameters,
    hybrid_applies,
    hybrid_online_steps,
    hybrid_parameters,
    mm_online_applies,
    mm_online_steps,
    predict_rates,
    sgd_online_steps,
)
from vfm_core.learning.training import (
    MapObjective,
    clip_per_well_,
    plain_optimizer,
    split_parameters,
)
from vfm_core.models import MODELS, ChokeModel, make_model
from vfm_core.timeutil import from_ns, to_ns, utc_timestamp

__all__ = [
    "WellLearner",
    "predict_many",
    "learn_many",
    "model_fixed_when_predicting",
    "phase_split",
    "PARAMETER_UNITS",
    "CHECKPOINT_FORMATS",
]

PARAMETER_UNITS: dict[str, str] = {name: p.unit for name, p in ph.PRIORS.items()} | {"a_max": "m2"}
#: the checkpoint formats :meth:`WellLearner.restore` reads (the first writes today's)
CHECKPOINT_FORMATS = ("vfm-well-learner/3", "vfm-well-learner/2", "vfm-well-learner/1")
#: the keys of :meth:`WellLearner.predict`'s answer, in order
_ANSWER_KEYS = ("q_total", "q_gas", "q_oil", "q_water", "q_total_std", "q_total_p05", "q_total_p95")


def phase_split(
    q_total: torch.Tensor, x: torch.Tensor, theta: dict[str, torch.Tensor] | None = None
) -> dict[str, torch.Tensor]:
    """Split total rates (Sm3/h) into gas, oil and water by the inputs' mass fractions.

    Q = mdot (eta_g/rho_g,sc + eta_o/rho_o + eta_w/rho_w), so each phase's share of Q is
    its term over the sum. Densities from ``theta``, by default the prior means: the fluid
    densities in which the mass fractions are expressed. The study and the service use the
    default, not a physics model's learned densities: those are identified only jointly
    with C_D (they absorb model error), and splitting with them added error wherever it
    was measured (Volve, mm with bayes: oil 13.9 % at the priors, 19.1 % learned; simulated
    fields: equal or worse by up to 0.4 points).
    """
    th = theta or {}

    def get(name: str) -> torch.Tensor:
        v = th.get(name)
        return torch.as_tensor(ph.PRIORS[name].mean if v is None else v, dtype=DTYPE)

    eta_gas, eta_oil = x[..., 4], x[..., 5]
    gas = eta_gas / ph.gas_density_standard(get("m_gas"))
    oil = eta_oil / get("rho_oil")
    wat = (1.0 - eta_gas - eta_oil) / get("rho_wat")
    total = gas + oil + wat
    return {
        "q_gas": q_total * gas / total,
        "q_oil": q_total * oil / total,
        "q_water": q_total * wat / total,
    }


@functools.cache
def _split_densities() -> tuple[float, float, float]:
    """The prior densities :func:`phase_split` divides by (standard gas, oil, water), kg/m3."""
    prior = {
        k: torch.as_tensor(ph.PRIORS[k].mean, dtype=DTYPE) for k in ("m_gas", "rho_oil", "rho_wat")
    }
    return (
        float(ph.gas_density_standard(prior["m_gas"])),
        float(prior["rho_oil"]),
        float(prior["rho_wat"]),
    )


def phase_split_numpy(q_total: np.ndarray, x: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`phase_split` at the prior densities on numpy arrays (``q_total`` [N], ``x``
    [N, 6]): the same operations in the same order, so the same numbers to the last bit,
    without a dozen small torch calls (a group of wells' predictions asks it once)."""
    rho_gas, rho_oil, rho_wat = _split_densities()
    eta_gas, eta_oil = x[:, 4], x[:, 5]
    gas = eta_gas / rho_gas
    oil = eta_oil / rho_oil
    wat = (1.0 - eta_gas - eta_oil) / rho_wat
    total = gas + oil + wat
    return {
        "q_gas": q_total * gas / total,
        "q_oil": q_total * oil / total,
        "q_water": q_total * wat / total,
    }


#: one prepared sample: its six inputs, its time (epoch ns) and the model's feature columns
_Row = tuple[list[float], int, list[float]]


def _epoch_ns(when: datetime | int) -> int:
    """Epoch nanoseconds of a sample's time: :func:`utc_timestamp`'s ``.value``, without a
    pandas Timestamp for a plain datetime (microseconds: exact integer arithmetic); an int
    is epoch ns already."""
    if type(when) is int:
        return when
    if type(when) is datetime:
        return to_ns(when)
    return int(utc_timestamp(when).value)


def _six(inputs: Sequence[float] | torch.Tensor) -> list[float]:
    """A sample's six inputs as floats (the same numbers ``torch.as_tensor`` would hold)."""
    try:
        values = inputs.reshape(-1).tolist() if isinstance(inputs, torch.Tensor) else inputs
        x = list(map(float, values))
    except (TypeError, ValueError):
        x = []
    if len(x) != 6:  # the tensor's own error says what is wrong
        torch.as_tensor(inputs, dtype=DTYPE).reshape(1, 1, 6)
        raise ValueError(f"A sample needs six inputs; got {inputs!r}.")
    return x


def _single(
    x: torch.Tensor,
    y: float,
    t_ns: int,
    well_test: bool,
    extra: torch.Tensor,
    names: tuple[str, ...],
) -> Batch:
    """One sample of one well as a batch."""
    return Batch(
        ["well"],
        x.reshape(1, 1, 6).to(DTYPE),
        torch.tensor([[y]], dtype=DTYPE),
        torch.tensor([[True]]),
        torch.tensor([[t_ns]], dtype=torch.int64),
        torch.tensor([[0]], dtype=torch.int64),
        torch.tensor([[well_test]]),
        extra.reshape(1, 1, -1).to(DTYPE),
        names,
    )


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
                "cannot hold it; use vfm_core.field_learner.FieldLearner (the service does so when "
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
        x, y, t, w, e, tracker = self._rows(x, y, time_ns, well_test, features, tracker)
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
        x, y, t, w, e, tracker = self._rows(x, y, time_ns, well_test, features, tracker)
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
        self._bump(last.to_pydatetime())
        self.method.start(int((last if base is None else utc_timestamp(base)).value))

    @staticmethod
    def _rows(
        x: torch.Tensor,
        y: torch.Tensor,
        t: torch.Tensor,
        well_test: torch.Tensor | None,
        features: torch.Tensor | None,
        tracker: FeatureTracker | None,
    ) -> tuple[
        torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, FeatureTracker
    ]:
        """History rows as stored tensors, with well-test flags, features and their tracker."""
        n = int(x.shape[0])
        x, y, t = x.reshape(n, 6).to(DTYPE), y.reshape(n).to(DTYPE), t.reshape(n)
        w = torch.zeros(n, dtype=torch.bool) if well_test is None else well_test.reshape(n).bool()
        if features is None or tracker is None:
            tracker = FeatureTracker()
            feats = [[0.0] * len(FeatureTracker.names) for _ in range(n)]
            for i in torch.argsort(t, stable=True).tolist():
                feats[i] = tracker.advance(int(t[i]), float(x[i, 4]), float(x[i, 5]))
                tracker.measured(int(t[i]), float(y[i]))
            features = torch.tensor(feats, dtype=DTYPE)
        return x, y, t, w, features.reshape(n, len(FeatureTracker.names)).to(DTYPE), tracker

    def _bump(self, when: datetime) -> None:
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
            self._bump(pd.Timestamp(until, tz="UTC").to_pydatetime(warn=False))
        return bool(done)

    # -- streaming ------------------------------------------------------------------------
    def predict(
        self, inputs: list[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        """Rates (Sm3/h) for one sample's inputs; all None until the model is ready.

        ``q_total`` and its phase split ``q_gas``, ``q_oil``, ``q_water``; with a method that
        gives intervals also ``q_total_std`` and the central 90 % interval ``q_total_p05``,
        ``q_total_p95`` (else None). A sample time ``when`` past the method's next scheduled
        retrain retrains first (on everything learned before that time), so the calendar of
        retrains matches ``vfm evaluate``.
        """
        out, row = self._prepare(inputs, when)
        if row is None:
            return out
        return self._answer(out, self.method.predict(self._batch_of(row)), row[0], 0)

    def _prepare(
        self, inputs: Sequence[float] | torch.Tensor, when: datetime | int | None
    ) -> tuple[dict[str, float | None], _Row | None]:
        """The side effects of :meth:`predict` before the model runs, in its order: the
        sample's features, then the retrains due. Returns the answer to fill and the sample
        as plain numbers (None while the model is not ready): inputs, time (ns, 0 for
        none) and the model's feature columns."""
        x = _six(inputs)
        ns = None if when is None else _epoch_ns(when)
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

    def _batch_of(self, row: _Row) -> Batch:
        """One prepared sample as a one-well batch (as a well test, see :meth:`predict`)."""
        x, at, extra = row
        return _single(
            torch.tensor(x, dtype=DTYPE),
            0.0,
            at,
            True,
            torch.tensor(extra, dtype=DTYPE),
            tuple(self.model.extra_columns),
        )

    @staticmethod
    def _answer(
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
        if not model_fixed_when_predicting(self) or not self.ready:
            raise ValueError(
                f"predict_block needs a ready model that predicting cannot change; {self.well} "
                f"({self.name}) is {'not ready' if not self.ready else 'retrained on a schedule'}."
            )
        x = np.asarray(inputs, dtype=float).reshape(-1, 6)
        t = np.asarray(times_ns, dtype=np.int64).reshape(-1)
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
        inputs: list[float] | torch.Tensor,
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
        ts, changed, batch = self._take(inputs, q_total, when, source)
        return self._learned(batch, ts, changed)

    def _take(
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
        batch = _single(
            x,
            float(q_total),
            ts.value,
            well_test,
            feats[0, self._cols],
            tuple(self.model.extra_columns),
        )
        return ts, changed, batch

    def _learned(self, batch: Batch, ts: pd.Timestamp, changed: bool) -> bool:
        """The rest of :meth:`learn`: the method learns from the measurement taken by
        :meth:`_take`; a new version if the model changed."""
        if bool(self.method.on_measurement(batch, self.memory).any()):
            self._bump(ts.to_pydatetime(warn=False))
            changed = True
        return changed

    def retrain(self, now: datetime | pd.Timestamp) -> None:
        """Retrain now on everything learned up to ``now`` (e.g. after a confirmed drift);
        scheduled retrains then count their period from ``now``."""
        ts = utc_timestamp(now)
        self.method.retrain(self.memory, int(ts.value) + 1)
        self.method.start(int(ts.value))
        self._bump(ts.to_pydatetime(warn=False))

    # -- state ----------------------------------------------------------------------------
    def physical_parameters(self) -> dict[str, dict[str, Any]]:
        """Named physical parameters (effects' as ``effect.name``): ``value`` (SI), ``unit``,
        ``std`` (the learning method's posterior standard deviation; None for a method that
        keeps no uncertainty), the bounds ``low`` and ``high`` learning may not cross (None
        for a set quantity such as ``a_max``), and ``at_bound``: True when the value sits
        within a thousandth of the range of a bound that is not also the prior's mean (the
        data push it beyond what physics allows: often a sign of a missing effect)."""
        priors = dict(ph.PRIORS)
        for e in getattr(self.model, "effects", []):
            priors.update({f"{e.name}.{k}": pr for k, pr in e.parameters.items()})
        sd = self.method.parameter_sd()
        out: dict[str, dict[str, Any]] = {}
        for name, v in self.model.physical_parameters().items():
            value = float(v[0])
            prior = priors.get(name)
            std = sd.get(name)
            entry: dict[str, Any] = {
                "value": value,
                "unit": prior.unit if prior is not None else PARAMETER_UNITS.get(name, ""),
                "std": float(std[0]) if std is not None else None,
                "low": prior.low if prior is not None else None,
                "high": prior.high if prior is not None else None,
                "at_bound": False,
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
        rest (MAPE, %), so the caller can see whether the change helps. The new learner
        carries the feature state on, and its version is this one's plus one.

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
            for key, spec_model, spec_effects, like in (
                ("before", self.model_name, self.effects, self),
                ("after", model, effects, new),
            ):
                trial = WellLearner(
                    self.well,
                    spec_model,
                    "ol",
                    train=budgeted(like.train),
                    online=like.online,
                    model_kwargs=like.model_kwargs,
                    seed=self.seed,
                    effects=spec_effects,
                )
                trial._fit_rows(self, cut, converge=spec_model == "mm")
                held = WellMemory(self.well, FeatureTracker.names, trial.model.extra_columns)
                held.copy_from(self.memory, test)
                q = trial.model.predict_batch(held.rows())[0]
                y = held.y
                ok = torch.abs(y) > 1e-9  # a zero rate has no relative error
                scores[key] = float((torch.abs(q - y)[ok] / torch.abs(y[ok])).mean() * 100.0)
        new._fit_rows(self, order, converge=model == "mm")
        new.features = FeatureTracker.from_state(self.features.state())
        new.version = self.version + 1
        new.n_updates = self.n_updates + 1
        new.last_update = self.last_update
        if self.last_update is not None:
            new.method.start(int(utc_timestamp(self.last_update).value))
        return new, scores

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
            x, y, t, w, e, tracker = cls._rows(p["x"], p["y"], p["t"], None, None, None)
            learner.memory.load({"x": x, "y": y, "t": t, "w": w, "e": e})
            learner.features = tracker
        return learner


#: :meth:`WellLearner.predict` as defined here (a subclass may answer its own way)
_WELL_PREDICT = WellLearner.predict


# -- many wells' predictions in one call ----------------------------------------------------------
Rates = dict[str, float | None]

#: a sample waiting for its group's model call: its place, learner, answer and row
_Waiting = tuple[int, "WellLearner", Rates, _Row]

#: the per-well state of ``bayes`` its predictions read (leading dimension: the well)
_BAYES_STATE = ("_P", "_h", "_last", "_noise", "_scale", "_started")


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
    before its prediction). The learners whose models have the same class and
    hyperparameters, and whose method predicts with the model alone (``ol``, ``pbl``,
    ``pbl:auto``) or is ``bayes`` with the same settings, then share one model call: their
    per-well parameters are stacked into one multi-well state. The answers equal the
    one-by-one answers (to rounding, 1e-12 relative). A learner may come more than once
    (a well's consecutive samples): if its next sample may change its model (a scheduled
    retrain, see :func:`model_fixed_when_predicting`), what waits is predicted first.
    Anything else (not a :class:`WellLearner`, a subclass with its own ``predict``, a
    model that cannot be stacked) answers through its own ``predict``.

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
            if _batchable(learner):
                out, row = learner._prepare(inputs[i], when)
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
    if not return_exceptions:
        for r in results:
            if isinstance(r, BaseException):
                raise r
    return results  # type: ignore[return-value]


def model_fixed_when_predicting(learner: Any) -> bool:
    """True when predicting cannot change ``learner``'s model: a :class:`WellLearner` whose
    method has no scheduled retrains (``ol``, ``bayes``). Several samples of such a well
    can then be predicted in one call (:func:`predict_many`); with ``pbl`` a sample may
    first retrain the model, so each sample waits for the one before."""
    return _batchable(learner) and (type(learner.method).retrain_due is LearningMethod.retrain_due)


def _batchable(learner: Any) -> bool:
    """A :class:`WellLearner` that predicts with :meth:`WellLearner.predict` itself (not a
    subclass's own, nor a replacement): its steps can be split around one model call."""
    return isinstance(learner, WellLearner) and type(learner).predict is _WELL_PREDICT


def _run_waiting(
    waiting: list[_Waiting],
    results: list[Rates | BaseException | None],
) -> None:
    """Predict the prepared samples, one model call per group of stackable learners."""
    groups: dict[tuple[Any, ...], list[int]] = {}
    for k, (_, learner, _, _) in enumerate(waiting):
        key = _group_key(learner)
        groups.setdefault(("alone", k) if key is None else key, []).append(k)
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
                forecast = learner.method.predict(learner._batch_of(row))
                results[i] = learner._answer(out, forecast, row[0], 0)
            except Exception as exc:
                results[i] = exc


def _group_key(learner: WellLearner) -> tuple[Any, ...] | None:
    """What learners must share to be predicted in one call; None: never stacked (kept
    on the learner while its model and method objects stay the same)."""
    method, model = learner.method, learner.model
    q = getattr(method, "_q", None)  # bayes: the drift its intervals use
    cached = learner.__dict__.get("_group")
    if cached is not None and cached[0] is method and cached[1] is model and cached[2] is q:
        return cached[3]  # type: ignore[no-any-return]
    key = _compute_group_key(learner)
    learner.__dict__["_group"] = (method, model, q, key)
    return key


def _compute_group_key(learner: WellLearner) -> tuple[Any, ...] | None:
    method, model = learner.method, learner.model
    predict = type(method).predict
    if predict is LearningMethod.predict:
        how: tuple[Any, ...] = ("model",)
    elif isinstance(method, BayesianFilter) and predict is BayesianFilter.predict:
        if model.gradient_free or method._dim == 0:
            how = ("model",)
        else:
            how = ("bayes", method.text, tuple(method._q.tolist()))
    else:
        return None
    return (
        type(model),
        learner.model_name,
        json.dumps(learner.effects),
        json.dumps(learner.model_kwargs, sort_keys=True, default=str),
        tuple(model.extra_columns),
        *how,
    )


class _Stacked(torch.nn.Module):
    """A model of the group's class for many wells, called with the wells' stacked tensors."""

    def __init__(self, learner: WellLearner) -> None:
        super().__init__()
        one = learner.model
        self.model = make_model(
            learner.model_name,
            ["well 1", "well 2"],
            seed=learner.seed,
            effects=list(learner.effects),
            **learner.model_kwargs,
        )
        mine = dict(one.named_parameters()) | dict(one.named_buffers())
        two = dict(self.model.named_parameters()) | dict(self.model.named_buffers())
        if set(mine) != set(two):
            raise ValueError(f"The model {one.name} cannot be rebuilt with the same tensors.")
        #: tensors with a leading well dimension: (name, path to their module, attribute)
        self.per_well: list[tuple[str, tuple[str, ...], str, bool]] = []
        #: tensors shared by every well of the model (e.g. the priors), taken from the first
        self.shared: list[tuple[str, tuple[str, ...], str, bool]] = []
        params = dict(one.named_parameters())
        for name, t in mine.items():
            t2 = two[name]
            *path, attr = name.split(".")
            where = (name, tuple(path), attr, name in params)
            if t.dim() > 0 and t.shape[0] == 1 and t2.shape[0] == 2 and t.shape[1:] == t2.shape[1:]:
                self.per_well.append(where)
            elif t.shape == t2.shape:
                self.shared.append(where)
            else:
                raise ValueError(f"The tensor {name} of {one.name} has no well dimension.")

    @staticmethod
    def _holder(model: torch.nn.Module, path: tuple[str, ...], is_param: bool) -> dict[str, Any]:
        """The parameter or buffer dict of the module at ``path`` under ``model``."""
        for p in path:
            model = model._modules[p]  # type: ignore[assignment]
        return model._parameters if is_param else model._buffers  # type: ignore[return-value]

    @staticmethod
    def _tensor(model: torch.nn.Module, path: tuple[str, ...], attr: str, is_param: bool) -> Any:
        return _Stacked._holder(model, path, is_param)[attr]

    def _places(self, model: torch.nn.Module) -> list[tuple[dict[str, Any], str]]:
        """Where ``model`` keeps each per-well tensor: its module's parameter or buffer dict
        and the name, kept on the model (a module's dicts live as long as the module, and a
        tensor put in their place is read from them)."""
        cached = model.__dict__.get("_vfm_places")
        if cached is not None and cached[0] is self.per_well:
            return cached[1]  # type: ignore[no-any-return]
        places = [
            (self._holder(model, path, is_param), attr) for _, path, attr, is_param in self.per_well
        ]
        model.__dict__["_vfm_places"] = (self.per_well, places)
        return places

    def state_of(self, models: list[ChokeModel]) -> dict[str, torch.Tensor]:
        """The models' tensors stacked along the well dimension (shared ones from the first)."""
        get = self._tensor
        places = self._places
        columns = zip(*[[d[a] for d, a in places(m)] for m in models], strict=True)
        state = {
            f"model.{name}": torch.cat(column, 0)
            for (name, _, _, _), column in zip(self.per_well, columns, strict=True)
        }
        for name, path, attr, is_param in self.shared:
            state[f"model.{name}"] = get(models[0], path, attr, is_param)
        return state

    def forward(self, batch: Batch) -> torch.Tensor:
        return predict_rates(self.model, batch)

    def call(self, state: dict[str, torch.Tensor], batch: Batch) -> torch.Tensor:
        """The rates for ``batch`` with ``state``'s tensors (:meth:`state_of`) in the
        model's place, then its own put back: what
        ``torch.func.functional_call(self, state, (batch,))`` gives, with a plain swap in
        the module's dicts instead of its per-call machinery. The stacked model is this
        thread's own (:func:`_stacked`) and its stacked updates use it too, so its own
        tensors must be back in place after every call."""
        slots = self.__dict__.get("_slots")
        if slots is None:
            slots = [
                (f"model.{name}", self._holder(self.model, path, is_param), attr)
                for name, path, attr, is_param in self.per_well + self.shared
            ]
            self.__dict__["_slots"] = slots
        own = [holder[attr] for _, holder, attr in slots]
        try:
            for key, holder, attr in slots:
                holder[attr] = state[key]
            return self.forward(batch)
        finally:
            for (_, holder, attr), tensor in zip(slots, own, strict=True):
                holder[attr] = tensor


class _Mean:
    """Stands in for a model inside a stacked ``bayes``: the mean is already computed."""

    gradient_free = False

    def __init__(self, mean: torch.Tensor) -> None:
        self.mean = mean

    def predict_batch(self, batch: Batch) -> torch.Tensor:
        return self.mean


_local = threading.local()


def _stacked(learner: WellLearner, key: tuple[Any, ...]) -> _Stacked | None:
    """The cached multi-well model for a group (one per thread: calls swap its tensors);
    None for a model that cannot be rebuilt for many wells."""
    cache: dict[tuple[Any, ...], _Stacked | None] | None = getattr(_local, "stacked", None)
    if cache is None:
        cache = _local.stacked = {}
    if key[:5] not in cache:
        if len(cache) >= 64:  # many model specifications in one process: start again
            cache.clear()
        try:
            cache[key[:5]] = _Stacked(learner)
        except Exception:
            cache[key[:5]] = None
    return cache[key[:5]]


def _predict_group(members: list[_Waiting], results: list[Rates | BaseException | None]) -> None:
    """One model call for learners of one group (see :func:`_group_key`)."""
    first = members[0][1]
    key = _group_key(first)
    assert key is not None
    stacked = _stacked(first, key)
    if stacked is None:
        raise ValueError(f"The model {first.name} cannot be stacked.")
    k = len(members)
    rows = [m[3] for m in members]
    # as the one-sample batches of WellLearner._batch_of, one row per well
    xs, ts, extras = zip(*rows, strict=True)
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
    state = stacked.state_of([m[1].model for m in members])
    stacked.model.wells = batch.wells
    with torch.no_grad():
        mean = stacked.call(state, batch)
    if key[5] == "bayes":
        method = copy.copy(first.method)
        for attr in _BAYES_STATE:
            setattr(method, attr, torch.cat([getattr(m[1].method, attr) for m in members], 0))
        method._model = _Mean(mean)  # type: ignore[assignment]
        forecast = method.predict(batch)
    else:
        forecast = Forecast(mean)
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


# -- many wells' online updates in one call -------------------------------------------------------
#: :meth:`WellLearner.learn` as defined here (a subclass may learn its own way)
_WELL_LEARN = WellLearner.learn

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
    retrains due, the features, the memory); then the learners whose models have the same
    class and hyperparameters (as in :func:`predict_many`) and the same method settings
    learn together, their per-well parameters stacked into one multi-well model:

    - ``ol`` with a plain Adam or SGD (no learning-rate schedule): the E optimiser steps,
      with the wells' optimiser states stacked (Adam's moments and each well's own step
      count, so its own bias correction); each well keeps its own gradient clipping and
      projection;
    - ``bayes``: the filter's Kalman step, with the wells' filter states stacked (as the
      study updates a field's wells in one call).

    The parameters and method states are then written back into each learner's own model
    and method, so its checkpoint and later one-by-one calls are what learning one by one
    leaves: the parameters, optimiser and filter states and later predictions equal it to
    rounding (1e-12 relative; a filter's covariance to 1e-12 of its largest entry). A
    learner that comes twice waits for its first measurement to be learned. Anything else
    (``pbl``, whose learn only stores the measurement; a subclass with its own ``learn``;
    a field-wide model's well; a model that cannot be stacked) learns through its own
    ``learn``, in order.

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
                ts, changed, batch = learner._take(inputs[i], q_totals[i], whens[i], source)
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
    if not return_exceptions:
        for r in results:
            if isinstance(r, BaseException):
                raise r
    return results  # type: ignore[return-value]


def _learn_batchable(learner: Any) -> bool:
    """A :class:`WellLearner` learning with :meth:`WellLearner.learn` itself, a gradient
    model, and ``ol`` or ``bayes`` exactly (whose updates :func:`_learn_group` runs for many
    wells at once)."""
    return (
        isinstance(learner, WellLearner)
        and type(learner).learn is _WELL_LEARN
        and type(learner.method) in (OnlineLearning, BayesianFilter)
        and not learner.model.gradient_free
    )


def _learn_key(learner: WellLearner) -> tuple[Any, ...] | None:
    """What learners must share to learn in one call: the model (as :func:`_group_key`)
    and the method's settings: for ``ol`` its online settings and the optimiser's
    hyperparameters, for ``bayes`` its text (every option); None: never stacked (``ol``
    with a schedule, an optimiser :func:`optimizer_step_` would not step itself, more than
    one parameter group; ``bayes`` on a model with nothing to filter)."""
    key = _group_key(learner)
    method = learner.method
    if key is None:
        return None
    if isinstance(method, BayesianFilter):
        if method._dim == 0:
            return None
        return (*key[:5], "bayes", method.text)
    if not isinstance(method, OnlineLearning):
        return None
    s = method.online
    opt = method._optimiser()
    if s.schedule_power != 0 or method._sched is not None or len(opt.param_groups) != 1:
        return None
    if not isinstance(opt, torch.optim.Adam | torch.optim.SGD) or not plain_optimizer(opt):
        return None
    group = opt.param_groups[0]
    hyper: tuple[Any, ...]
    if isinstance(opt, torch.optim.Adam):
        hyper = ("adam", group["lr"], tuple(group["betas"]), group["eps"])
    else:
        hyper = ("sgd", group["lr"], None, None)
    # the last four: the optimiser, its rate, Adam's betas and epsilon (see _online_steps)
    return (*key[:5], "ol", s.steps, s.noise, s.max_grad_norm, *hyper)


def _learn_waiting(waiting: list[_Taken], results: list[bool | BaseException | None]) -> None:
    """Learn the taken measurements, one multi-well update per group of stackable learners."""
    groups: dict[tuple[Any, ...], list[int]] = {}
    for k, (_, learner, _, _, _) in enumerate(waiting):
        try:
            key = _learn_key(learner)
        except Exception:
            key = None
        groups.setdefault(("alone", k) if key is None else key, []).append(k)
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
                results[i] = learner._learned(batch, ts, changed)
            except Exception as exc:
                results[i] = exc


def _learn_group(
    members: list[_Taken], key: tuple[Any, ...], results: list[bool | BaseException | None]
) -> list[_Taken]:
    """The updates of one group's learners (see :func:`_learn_key`) as one multi-well
    update; returns the members left to learn one by one (those not ready yet, or all
    when fewer than two are ready). No learner's parameters or method state change until
    the whole update has run, so a failure leaves the group to the one-by-one path."""
    first = members[0][1]
    stacked = _stacked(first, _group_key(first))  # type: ignore[arg-type]
    if stacked is None:
        raise ValueError(f"The model {first.name} cannot be stacked.")
    model = stacked.model
    online = key[5] == "ol"
    ready: list[_Taken] = []
    rest: list[_Taken] = []
    for m in members:
        learner, batch = m[1], m[2]
        # what the method's _learn does first: set-up statistics (and ol's optimiser)
        learner.model.setup(batch)
        if online:
            learner.method._optimiser()  # type: ignore[attr-defined]
        (ready if learner.ready and int(batch.count()[0]) > 0 else rest).append(m)
    if len(ready) < 2:
        return rest + ready
    if any(w[3] for w in stacked.shared):
        raise ValueError(f"The model {first.name} has parameters shared by its wells.")
    learners = [m[1] for m in ready]
    models = [lrn.model for lrn in learners]
    get = stacked._tensor
    with torch.no_grad():
        for name, path, attr, is_param in stacked.per_well + stacked.shared:
            if (name, path, attr, is_param) in stacked.shared:
                value = get(models[0], path, attr, is_param)
            else:
                value = torch.cat([get(mo, path, attr, is_param) for mo in models], 0)
            if is_param:
                get(model, path, attr, True).data = value.detach().clone()
            else:
                stacked._holder(model, path, False)[attr] = value
    model.wells = [lrn.well for lrn in learners]
    batches = [m[2] for m in ready]
    batch = Batch(
        model.wells,
        torch.cat([b.x for b in batches], 0),
        torch.cat([b.y for b in batches], 0),
        torch.cat([b.mask for b in batches], 0),
        torch.cat([b.time_ns for b in batches], 0),
        torch.cat([b.row for b in batches], 0),
        torch.cat([b.well_test for b in batches], 0),  # type: ignore[misc]
        torch.cat([b.extra for b in batches], 0),  # type: ignore[misc]
        batches[0].extra_names,
    )
    params = [w for w in stacked.per_well if w[3]]
    if online:
        finish = _online_steps(stacked, learners, batch, key)
        changed = [True] * len(ready)
    else:
        finish, changed = _bayes_update(stacked, learners, batch)
    # every step ran: write each well's parameters back, in place (one call per parameter
    # for all wells), then the method's state
    with torch.no_grad():
        for _, path, attr, _ in params:
            p = get(model, path, attr, True)
            p.grad = None
            torch._foreach_copy_([get(mo, path, attr, True) for mo in models], list(p.split(1, 0)))
    finish()
    for (i, learner, _, ts, was), moved in zip(ready, changed, strict=True):
        if moved:
            if online:
                learner.method.updates += 1  # type: ignore[attr-defined]
            learner._bump(ts.to_pydatetime(warn=False))
        results[i] = was or moved
    return rest


def _same_parameters(a: list[torch.nn.Parameter], b: list[torch.nn.Parameter]) -> bool:
    """True when ``a`` and ``b`` hold the same parameters (in any order)."""
    return len(a) == len(b) and {id(p) for p in a} == {id(p) for p in b}


def _online_steps(
    stacked: _Stacked, learners: list[WellLearner], batch: Batch, key: tuple[Any, ...]
) -> Any:
    """``ol``'s E optimiser steps (``OnlineLearning._learn``) on the stacked model, each well
    with its own Adam moments and step count (its own bias correction), its own gradient
    clipping and projection. Returns what writes the optimiser states back."""
    model, get = stacked.model, stacked._tensor
    models = [lrn.model for lrn in learners]
    trainable = [w for w in stacked.per_well if w[3] and get(model, w[1], w[2], True).requires_grad]
    if not trainable:
        raise ValueError("The model has no parameters to learn.")
    opts = [lrn.method._optimiser() for lrn in learners]  # type: ignore[attr-defined]
    kind, lr, betas, eps = key[-4:]
    adam = kind == "adam"
    k = len(learners)
    # the stacked parameters and, per parameter, the wells' Adam states and step counts
    params: list[torch.nn.Parameter] = []
    own: list[list[torch.nn.Parameter]] = []  # per stacked parameter: each learner's own
    moments: list[tuple[torch.Tensor, torch.Tensor] | None] = []
    steps: list[list[float]] = []
    for _, path, attr, _ in trainable:
        mine = [get(mo, path, attr, True) for mo in models]
        params.append(get(model, path, attr, True))
        own.append(mine)
        if not adam:
            moments.append(None)
            steps.append([])
            continue
        states = [opt.state.get(q) or {} for opt, q in zip(opts, mine, strict=True)]
        pairs = list(zip(states, mine, strict=True))
        moments.append(
            (
                torch.cat([st["exp_avg"] if st else torch.zeros_like(q) for st, q in pairs], 0),
                torch.cat([st["exp_avg_sq"] if st else torch.zeros_like(q) for st, q in pairs], 0),
            )
        )
        steps.append([float(st["step"]) if st else 0.0 for st in states])
    stepped = [0] * len(params)  # steps each parameter took (torch's Adam skips no-gradient ones)
    s = learners[0].method.online  # type: ignore[attr-defined]
    groups = split_parameters(model)
    objective = MapObjective(model, batch, s.noise, True, batch.count().to(DTYPE))
    factors: dict[tuple[float, ...], tuple[torch.Tensor, torch.Tensor]] = {}
    if len(params) == 1 and mm_online_applies(model):  # the same steps, compiled
        before = np.array(steps[0] if adam else [0.0] * k, dtype=np.float64)
        mm_online_steps(
            model,
            batch,
            moments[0],
            before,
            np.zeros(k, dtype=bool),
            steps=s.steps,
            noise=s.noise,
            lr=lr,
            betas=betas if adam else (0.9, 0.999),
            eps=eps if adam else 1e-8,
            max_norm=s.max_grad_norm,
        )
        if adam:
            steps[0] = before.tolist()
        stepped[0] = s.steps
    elif hybrid_applies(model) and _same_parameters(params, order := hybrid_parameters(model)):
        index = [[id(p) for p in params].index(id(q)) for q in order]
        before_all = np.array([steps[j] if adam else [0.0] * k for j in index], dtype=np.float64)
        hybrid_online_steps(  # the same steps, compiled
            model,
            batch,
            [moments[j] for j in index] if adam else None,  # type: ignore[misc, arg-type]
            before_all,
            np.zeros(k, dtype=bool),
            steps=s.steps,
            noise=s.noise,
            lr=lr,
            betas=betas if adam else (0.9, 0.999),
            eps=eps if adam else 1e-8,
            max_norm=s.max_grad_norm,
            params=order,
        )
        for j in index:
            stepped[j] = s.steps
    elif (
        not adam
        and all(getattr(lrn.method, "_nn", False) and lrn.method._compiled for lrn in learners)  # type: ignore[attr-defined]
        and _same_parameters(params, fit_parameters(model) or [])
    ):
        # the plain nn or lr with SGD: the same steps, compiled, as each learner's own
        # OnlineLearning takes them one by one
        sgd_online_steps(
            model, batch, np.zeros(k, dtype=bool), steps=s.steps, lr=lr, max_norm=s.max_grad_norm
        )
        stepped = [s.steps] * len(params)
    for _ in range(0 if stepped[0] else s.steps):
        objective.gradients_(params)
        clip_per_well_(model, s.max_grad_norm, groups)
        with torch.no_grad():
            for j, p in enumerate(params):
                g = p.grad
                if g is None:  # no gradient this step: torch's Adam skips the parameter
                    continue
                stepped[j] += 1
                if not adam:
                    p.add_(g, alpha=-lr)
                    continue
                beta1, beta2 = betas
                exp_avg, exp_avg_sq = moments[j]  # type: ignore[misc]
                counts = steps[j] = [c + 1.0 for c in steps[j]]
                exp_avg.lerp_(g, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(g, g, value=1 - beta2)
                fk = (p.dim(), *counts)
                if fk not in factors:  # each well's bias correction, as torch's Adam's
                    shape = (k, *([1] * (p.dim() - 1)))
                    size = [-(lr / (1 - beta1**c)) for c in counts]
                    root = [(1 - beta2**c) ** 0.5 for c in counts]
                    factors[fk] = (
                        torch.tensor(size, dtype=p.dtype).reshape(shape),
                        torch.tensor(root, dtype=p.dtype).reshape(shape),
                    )
                neg_step_size, bias_correction2_sqrt = factors[fk]
                # torch: param.addcdiv_(exp_avg, denom, value=-step_size), per well here
                denom = exp_avg_sq.sqrt().div_(bias_correction2_sqrt).add_(eps)
                p.addcdiv_(exp_avg * neg_step_size, denom)
        model.project_()

    def finish() -> None:
        """Each well's optimiser state, in place (the learners' tensors stay their own)."""
        if not adam:
            return
        scalar = _torch_optimizer._get_scalar_dtype()
        with torch.no_grad():
            for j in range(len(params)):
                if not stepped[j]:
                    continue
                exp_avg, exp_avg_sq = moments[j]  # type: ignore[misc]
                states = [opt.state[q] for opt, q in zip(opts, own[j], strict=True)]
                for st, q in zip(states, own[j], strict=True):
                    if not st:  # its first step: the state torch's Adam would create
                        st["step"] = torch.tensor(0.0, dtype=scalar)
                        st["exp_avg"] = torch.zeros_like(q, memory_format=torch.preserve_format)
                        st["exp_avg_sq"] = torch.zeros_like(q, memory_format=torch.preserve_format)
                # (integer step counts: adding them at once is adding one per step)
                torch._foreach_add_([st["step"] for st in states], float(stepped[j]))
                torch._foreach_copy_([st["exp_avg"] for st in states], list(exp_avg.split(1, 0)))
                torch._foreach_copy_(
                    [st["exp_avg_sq"] for st in states], list(exp_avg_sq.split(1, 0))
                )

    return finish


#: the per-well state of ``bayes`` its updates change (leading dimension: the well)
_BAYES_LEARN_STATE = (*_BAYES_STATE, "_run")


def _bayes_update(
    stacked: _Stacked, learners: list[WellLearner], batch: Batch
) -> tuple[Any, list[bool]]:
    """``bayes``'s Kalman step (``BayesianFilter._learn``, written for many wells) on the
    stacked model with the wells' filter states stacked. Returns what writes the states
    back, and which wells' models changed."""
    first = learners[0].method
    assert isinstance(first, BayesianFilter)
    method = copy.copy(first)
    method._model = stacked.model
    method._rebind(stacked.model)  # its filter blocks: the stacked model's parameters
    methods: list[BayesianFilter] = [lrn.method for lrn in learners]  # type: ignore[misc]
    for attr in _BAYES_LEARN_STATE:
        setattr(method, attr, torch.cat([getattr(m, attr) for m in methods], 0))
    method._counts = {
        name: torch.cat([m._counts[name] for m in methods], 0) for name in first._counts
    }
    changed = method._learn(batch, None)

    def finish() -> None:
        for attr in _BAYES_LEARN_STATE:
            rows = getattr(method, attr).split(1, 0)
            for m, row in zip(methods, rows, strict=True):
                setattr(m, attr, row.clone())
        for name, value in method._counts.items():
            for m, row in zip(methods, value.split(1, 0), strict=True):
                m._counts[name] = row.clone()

    return finish, [bool(c) for c in changed.tolist()]
