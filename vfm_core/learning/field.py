"""A field-wide model (``mtl``) with its learning method, fed one message at a time.

:class:`FieldLearner` is the streaming counterpart of what
:func:`vfm_core.jobs.study.run_prequential` does with a shared model: one multi-well model
(its shared network plus a task vector per well) over the wells it serves, and its bound
learning method. Each well is answered through a :class:`FieldWell`, a facade with the
public surface of :class:`vfm_core.learning.streaming.WellLearner` that the service uses
(``predict``, ``learn``, ``retrain``, ``version``, ``ready``, ``memory``, ``checkpoint``,
...), so the service treats a well of the field like any other well.

How it learns, as the study does, so that a replay reproduces ``vfm evaluate``:

- **Per-measurement methods** (``ol``, ``bayes``) learn in *rounds of one UTC day*: a
  measurement is held until the field's day ends (the first message of any well dated on
  a later day), and the day's measurements of every well are then learned together in
  one call. Predictions inside a day therefore use the parameters of the previous day's
  end. A measurement that arrives after its day has been closed (messages of different
  wells out of time order) is learned with its round all the same when that round is the
  one closed last (the model goes back to the state before it and learns it again: only
  the predictions made meanwhile used the round without it); one later still joins the
  round still open.
- **Periodic batch learning** (``pbl:<period>``) keeps every measurement and retrains the
  whole field when the first message at or after the next scheduled retrain arrives, on
  everything measured before that time (the study's calendar: ``start`` + k periods).
  As in the study, a well with no model yet starts predicting at the next retrain. A field
  with no history fit starts its calendar at its first measurement and predicts from its
  first retrain.

A well first seen live gets a new task vector at its prior (the model grows by one well;
the method's per-well state grows with it, the new well taking the field's retrain
calendar and iteration count). It predicts once it has been learned from.

State is tensors and plain values only: :meth:`FieldLearner.checkpoint` returns bytes
that :meth:`FieldLearner.restore` reads back with ``torch.load(weights_only=True)``; the
checkpoint holds the whole field (model, method, every well's remembered measurements,
the round still open and how many measurements of each well were learned).
"""

from __future__ import annotations

import copy
import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import replace
from datetime import datetime
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.features import FeatureTracker
from vfm_core.learning import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    NEVER,
    LearningMethod,
    OnlineSettings,
    TrainSettings,
    WellMemory,
    fit_batch,
    parse_method,
)
from vfm_core.learning.streaming import Learner, phase_split
from vfm_core.models import MODELS, ChokeModel, make_model
from vfm_core.timeutil import utc_timestamp

__all__ = ["FieldLearner", "FieldWell", "FIELD_CHECKPOINT_FORMAT", "DAY_NS"]

#: the checkpoint format :meth:`FieldLearner.checkpoint` writes and :meth:`FieldLearner.restore` reads
FIELD_CHECKPOINT_FORMAT = "vfm-field-learner/1"
#: one UTC day in nanoseconds: the length of a learning round of a per-measurement method
DAY_NS = 86_400 * 10**9
#: pads an empty well's rows in a batch (finite through every model; masked out anyway)
_PAD = (0.5, 100.0, 30.0, 60.0, 0.1, 0.6)
#: the buffers of every model that hold one row per well (ChokeModel's)
_PER_WELL_BUFFERS = ("ready", "y_scale", "x_mean", "x_std")
_OUTPUTS = ("q_total", "q_gas", "q_oil", "q_water", "q_total_std", "q_total_p05", "q_total_p95")


class FieldLearner:
    """A shared (field-wide) model and its learning method over the wells it serves.

    ``model`` must be a registered model with shared parameters (``mtl``); ``method`` a
    learning method the streaming learner runs. ``wells`` may be given up front (in the
    order ``vfm evaluate`` would see them) or added as they appear (:meth:`well`).
    """

    def __init__(
        self,
        model: str = "mtl",
        method: str = "ol",
        *,
        wells: Sequence[str] = (),
        train: TrainSettings | None = None,
        online: OnlineSettings | None = None,
        model_kwargs: dict[str, Any] | None = None,
        seed: int = 0,
    ) -> None:
        if model not in MODELS:
            raise ConfigError(f"Unknown model '{model}'; choose one of {', '.join(MODELS)}.")
        if not MODELS[model].shared:
            raise ConfigError(
                f"Model '{model}' keeps its parameters per well; run it with "
                "vfm_core.learning.streaming.WellLearner, one learner per well."
            )
        meth = parse_method(method)
        if not meth.streaming:
            raise ConfigError(
                f"The learning method '{meth.text}' cannot run in the streaming learner."
            )
        self.model_name = model
        self.method_text = meth.text
        self.train = train or DEFAULT_TRAIN[model]
        self.online = online or DEFAULT_ONLINE[model]
        self.model_kwargs = dict(model_kwargs or {})
        self.seed = seed
        self.wells: list[str] = []
        self._index: dict[str, int] = {}
        self.model: ChokeModel = make_model(model, [], seed=seed, **self.model_kwargs)
        self.method: LearningMethod = meth.bind(self.model, train=self.train, online=self.online)
        #: per well: every measurement learned from (inputs, rate, time, well test)
        self.memories: dict[str, WellMemory] = {}
        #: per well: how many measurements :meth:`learn` took (history rows not counted)
        self.n_learned: dict[str, int] = {}
        self._facades: dict[str, FieldWell] = {}
        #: the open round (per-measurement methods): its UTC day and its measurements
        self._day: int | None = None
        self._held: list[tuple[int, list[float], float, int, bool]] = []
        #: the round closed last: its day, its measurements, and the model's and the method's
        #: state before it (None after any other change of the model)
        self._undo: tuple[int, list[Any], dict[str, Any], dict[str, Any]] | None = None
        self.version = 0
        self.n_updates = 0
        self.last_update: datetime | None = None
        self.add(wells)

    # -- what it is ---------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return str(self.model.name)

    @property
    def rounds(self) -> bool:
        """True when the method learns per measurement, in day rounds (else at retrains only)."""
        return bool(self.method.per_measurement or self.model.gradient_free)

    def is_ready(self, well: str) -> bool:
        """True once ``well`` has been learned from (before, the model cannot answer for it)."""
        ready: torch.Tensor = self.model.ready  # type: ignore[assignment]
        return bool(ready[self._index[well]])

    def __contains__(self, well: object) -> bool:
        return well in self._index

    # -- wells ----------------------------------------------------------------------------------
    def well(self, well: str) -> FieldWell:
        """The facade of ``well``; a well not in the field yet is added at its prior."""
        facade = self._facades.get(well)
        if facade is None:
            if well not in self._index:
                self._grow([well])
            facade = self._facades[well] = FieldWell(self, well)
        return facade

    def fresh(self, well: str) -> FieldWell:
        """The facade of ``well`` at its prior, with nothing learned or remembered: a well new
        to the field is added; one the field knew (its id purged and used again) is reset
        (its own parameters and the method's state for it as a new well's; the shared
        network keeps what it learned)."""
        if well in self._index:
            self._reset(well)
        return self.well(well)

    def _reset(self, well: str) -> None:
        self._undo = None
        j, n = self._index[well], len(self.wells)
        model = make_model(self.model_name, self.wells, seed=self.seed, **self.model_kwargs)
        own = {id(p) for p in self.model.per_well_parameters()}
        rows = {k for k, p in self.model.named_parameters() if id(p) in own}
        rows |= set(_PER_WELL_BUFFERS)
        state, prior = self.model.state_dict(), model.state_dict()
        with torch.no_grad():
            for key in rows & set(state):
                state[key][j] = prior[key][j]
        self.model.load_state_dict(state)
        method = parse_method(self.method_text).bind(model, train=self.train, online=self.online)
        current, start = self.method.state_dict(), method.state_dict()
        others = torch.arange(n) != j
        pairs = [(v, start.get(k)) for k, v in current.items() if k != "optimizer"]
        pairs += [
            (v, start[k].get(kk))
            for k, sub in current.items()
            if k != "optimizer" and isinstance(sub, dict) and isinstance(start.get(k), dict)
            for kk, v in sub.items()
        ]
        for value, initial in pairs:
            if isinstance(value, torch.Tensor) and isinstance(initial, torch.Tensor):
                if value.dim() >= 1 and value.shape[0] == n and initial.shape == value.shape:
                    value[j] = initial[j]
        for key, pick in (("iterations", torch.max), ("next", torch.min)):
            value = current.get(key)
            if isinstance(value, torch.Tensor) and bool(others.any()):
                value[j] = pick(value[others])
        chosen_on = current.get("chosen_on")
        if isinstance(chosen_on, torch.Tensor) and chosen_on.numel() == n:
            chosen_on[j] = 0  # it has no measurement now
        positions = _per_well_indices(self.model)
        for idx, entry in (current.get("optimizer") or {}).get("state", {}).items():
            if int(idx) in positions:
                for value in entry.values():
                    if isinstance(value, torch.Tensor) and value.dim() >= 1 and value.shape[0] == n:
                        value[j] = 0
        self.method.load_state_dict(current)
        self.memories[well] = WellMemory(well, FeatureTracker.names, self.model.extra_columns)
        self.n_learned[well] = 0
        self._held = [h for h in self._held if h[0] != j]

    def add(self, wells: Sequence[str]) -> None:
        """Add the wells not in the field yet, each at its prior, in one step (adding a
        thousand wells one by one would rebuild the model a thousand times)."""
        self._grow(list(dict.fromkeys(str(w) for w in wells)))

    def _grow(self, new: Sequence[str]) -> None:
        """Add wells: a model over the larger field holding the same shared parameters and
        the old wells' own, and the method's per-well state grown with it."""
        new = [w for w in new if w not in self._index]
        if not new:
            return
        self._undo = None  # a state of fewer wells
        old_n = len(self.wells)
        wells = [*self.wells, *new]
        model = make_model(self.model_name, wells, seed=self.seed, **self.model_kwargs)
        if old_n:
            model.load_state_dict(_grown(self.model.state_dict(), model.state_dict(), old_n))
        method = parse_method(self.method_text).bind(model, train=self.train, online=self.online)
        if old_n:
            per_well = _per_well_indices(model)
            state = _grown_method(
                self.method.state_dict(), method.state_dict(), old_n, len(wells), per_well
            )
            method.load_state_dict(state)
        self.model, self.method, self.wells = model, method, wells
        self._index = {w: j for j, w in enumerate(wells)}
        for w in new:
            self.memories[w] = WellMemory(w, FeatureTracker.names, self.model.extra_columns)
            self.n_learned.setdefault(w, 0)

    # -- the Memory protocol (what a retrain reads) ---------------------------------------------
    def batch(self, until_ns: int, window_ns: int | None = None) -> Batch:
        """Every remembered measurement before ``until_ns`` (not older than ``window_ns``), as
        a padded batch over the field's wells, each well's rows in time order."""
        rows = []
        for w in self.wells:
            mem = self.memories[w]
            t = mem.t
            keep = t < until_ns
            if window_ns is not None:
                keep &= t >= until_ns - window_ns
            rows.append((mem.x[keep], mem.y[keep], t[keep], mem.well_test[keep]))
        return _pack(self.wells, rows, self.model.extra_columns)

    # -- history --------------------------------------------------------------------------------
    def fit_history(
        self,
        rows: Mapping[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
        until: datetime | pd.Timestamp | None = None,
        train: TrainSettings | None = None,
    ) -> None:
        """The initial fit of the whole field, as ``vfm evaluate`` fits before its split.

        ``rows``: per well (in the order the field should hold them: the order in which the
        wells first appear in the history), its measured rows as inputs [N, 6], rates [N]
        Sm3/h, times [N] epoch ns and well-test flags [N], in time order. ``until``: the
        split (``model.history_until``), from which the retrain calendar counts; without
        it, from the last history row. ``train``: the settings of this fit (default the
        field's). Only a field that has not learned yet can be fitted.
        """
        if self.version:
            raise ConfigError(
                "The field has already learned; a history fit would discard it. Build a new "
                "FieldLearner to fit on the history."
            )
        order = [w for w in rows if int(rows[w][0].shape[0]) > 0]
        if not order:
            return
        # the wells in the order of the history (then those known without history): the
        # order of the study's field, so that its sums run the same way
        wells = [*order, *(w for w in self.wells if w not in rows)]
        self.wells, self._index = [], {}
        self.model = make_model(self.model_name, [], seed=self.seed, **self.model_kwargs)
        self._grow(wells)
        t_max = 0
        for w in order:
            x, y, t, wt = rows[w]
            n = int(x.shape[0])
            feats = torch.zeros(n, len(FeatureTracker.names), dtype=DTYPE)
            self.memories[w].append(x.reshape(n, 6).to(DTYPE), y.reshape(n).to(DTYPE), t, wt, feats)
            t_max = max(t_max, int(t.max()))
        base = None if until is None else utc_timestamp(until)
        until_ns = t_max + 1 if base is None else int(base.value)
        window = None if self.method.window is None else int(self.method.window.value)
        initial = self.batch(until_ns, window)
        summary = fit_batch(self.model, initial, train or self.train)
        self.method.adopt(initial, summary["iterations"])
        self.method.start(t_max if base is None else int(base.value))
        self._bump(pd.Timestamp(t_max, tz="UTC").to_pydatetime())

    def remember(
        self,
        well: str,
        x: Any,
        y: Any,
        time_ns: Any,
        well_test: Any = None,
    ) -> None:
        """Keep measured rows of ``well`` for later retrains without learning from them now
        (inputs [N, 6], rates [N] Sm3/h, times [N] epoch ns, well-test flags [N]); e.g. the
        history of a well added to a field that has already learned."""
        self.well(well)
        xt = torch.as_tensor(x, dtype=DTYPE).reshape(-1, 6)
        n = int(xt.shape[0])
        wt = torch.zeros(n, dtype=torch.bool) if well_test is None else torch.as_tensor(well_test)
        self.memories[well].append(
            xt,
            torch.as_tensor(y, dtype=DTYPE).reshape(n),
            torch.as_tensor(time_ns, dtype=torch.int64).reshape(n),
            wt.reshape(n).bool(),
            torch.zeros(n, len(FeatureTracker.names), dtype=DTYPE),
        )

    # -- streaming ------------------------------------------------------------------------------
    def advance(self, t_ns: int) -> bool:
        """The field's clock reaches ``t_ns``: close the open round if its day has ended, and
        run the scheduled retrains due by then. True when the model changed."""
        changed = False
        if self.rounds:
            day = t_ns // DAY_NS
            if self._day is None or day > self._day:
                changed |= self._close_round()
                self._day = day
        before = self.method.n_retrains
        self.method.retrain_due(self, torch.full((len(self.wells),), t_ns, dtype=torch.int64))
        new = self.method.n_retrains - before
        if new > 0:
            self._undo = None
        for until in self.method.retrains[-new:] if new > 0 else []:
            self._bump(pd.Timestamp(until, tz="UTC").to_pydatetime(warn=False))
            changed = True
        return changed

    def flush(self) -> bool:
        """Learn the open round now, without waiting for its day to end. True if the model changed."""
        return self._close_round()

    def _close_round(self) -> bool:
        """Learn the held measurements of every well in one call (the study's round), keeping
        the state from before, so that a measurement of this day that arrives late can
        still be learned with its round (:meth:`learn`)."""
        if not self._held:
            return False
        held, self._held = self._held, []
        day = held[0][3] // DAY_NS if self._day is None else self._day
        self._undo = (
            day,
            held,
            copy.deepcopy(self.model.state_dict()),
            copy.deepcopy(self.method.state_dict()),
        )
        return self._learn_round(held)

    def _learn_round(self, held: list[tuple[int, list[float], float, int, bool]]) -> bool:
        per_well: list[list[tuple[list[float], float, int, bool]]] = [[] for _ in self.wells]
        for j, x, y, t, wt in held:
            per_well[j].append((x, y, t, wt))
        rows = []
        for items in per_well:
            items.sort(key=lambda item: item[2])  # a well's rows in time order, as in the study
            n = len(items)
            rows.append(
                (
                    torch.tensor([i[0] for i in items], dtype=DTYPE).reshape(n, 6),
                    torch.tensor([i[1] for i in items], dtype=DTYPE),
                    torch.tensor([i[2] for i in items], dtype=torch.int64),
                    torch.tensor([i[3] for i in items], dtype=torch.bool),
                )
            )
        batch = _pack(self.wells, rows, self.model.extra_columns)
        changed = self.method.on_measurement(batch, self)
        if bool(changed.any()):
            self._bump(pd.Timestamp(max(h[3] for h in held), tz="UTC").to_pydatetime(warn=False))
            return True
        return False

    def _relearn_round(self, item: tuple[int, list[float], float, int, bool]) -> bool:
        """A measurement of the round that closed last arrived late: back to the state before
        that round, and learn the round again with it."""
        assert self._undo is not None
        day, held, model_state, method_state = self._undo
        self.model.load_state_dict(model_state)
        self.method.load_state_dict(method_state)
        held = [*held, item]
        self._undo = (day, held, copy.deepcopy(model_state), copy.deepcopy(method_state))
        return self._learn_round(held)

    def predict(
        self, well: str, inputs: Sequence[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        """Rates (Sm3/h) of ``well`` at one sample's inputs, as :meth:`WellLearner.predict`."""
        if when is not None:
            self.advance(int(utc_timestamp(when).value))
        out: dict[str, float | None] = dict.fromkeys(_OUTPUTS)
        j = self._index[well]
        if not self.is_ready(well):
            return out
        x = torch.as_tensor(inputs, dtype=DTYPE).reshape(6)
        fast = self._one_well(j, x)
        if fast is not None:
            out["q_total"] = fast
            q1 = torch.tensor([[fast]], dtype=DTYPE)
            out.update({k: float(v[0, 0]) for k, v in phase_split(q1, x.reshape(1, 1, 6)).items()})
            return out
        t = 0 if when is None else int(utc_timestamp(when).value)
        n_w = len(self.wells)
        mask = torch.zeros(n_w, 1, dtype=torch.bool)
        mask[j, 0] = True
        # the sample as if a well test measured it: the best estimate of the true rate
        batch = Batch(
            list(self.wells),
            x.reshape(1, 1, 6).expand(n_w, 1, 6).clone(),
            torch.zeros(n_w, 1, dtype=DTYPE),
            mask,
            torch.full((n_w, 1), t, dtype=torch.int64),
            torch.full((n_w, 1), -1, dtype=torch.int64),
            mask.clone(),
            torch.zeros(n_w, 1, len(self.model.extra_columns), dtype=DTYPE),
            tuple(self.model.extra_columns),
        )
        forecast = self.method.predict(batch)
        q = forecast.mean[j : j + 1, :1]
        out["q_total"] = float(q[0, 0])
        out.update({k: float(v[0, 0]) for k, v in phase_split(q, x.reshape(1, 1, 6)).items()})
        if forecast.std is not None:
            out["q_total_std"] = float(forecast.std[j, 0])
        if forecast.p05 is not None and forecast.p95 is not None:
            out["q_total_p05"] = float(forecast.p05[j, 0])
            out["q_total_p95"] = float(forecast.p95[j, 0])
        return out

    def _one_well(self, j: int, x: torch.Tensor) -> float | None:
        """The rate (Sm3/h) of well ``j`` at inputs ``x`` computed on that well alone (its own
        parameters and statistics with the shared ones), or None where that is not the
        method's prediction (a method with intervals, a model reading more than the six
        inputs): a prediction then costs the same for ten wells or a thousand."""
        model, method = self.model, self.method
        if type(method).predict is not LearningMethod.predict:
            return None
        if type(model).forward_batch is not ChokeModel.forward_batch:
            return None
        own = {id(p) for p in model.per_well_parameters()}
        mine: dict[str, torch.Tensor] = {
            name: p[j : j + 1] for name, p in model.named_parameters() if id(p) in own
        }
        mine.update(
            {name: b[j : j + 1] for name, b in model.named_buffers() if name in _PER_WELL_BUFFERS}
        )
        with torch.no_grad():
            q = torch.func.functional_call(model, mine, (x.reshape(1, 1, 6),))
        return float(q[0, 0])

    def learn(
        self,
        well: str,
        inputs: Sequence[float] | torch.Tensor,
        q_total: float,
        when: datetime | pd.Timestamp,
        source: str = "mpfm",
    ) -> bool:
        """Take one measured rate (Sm3/h) of ``well`` paired with the inputs at its time.

        The measurement is remembered at once (for retrains); a per-measurement method
        learns it with the rest of its day when the day ends, ``pbl`` at its next retrain.
        Returns True when the model changed now (a round closed or a retrain ran first).
        """
        t = int(utc_timestamp(when).value)
        changed = self.advance(t)
        j = self._index[well]
        x = [float(v) for v in torch.as_tensor(inputs, dtype=DTYPE).reshape(6).tolist()]
        well_test = source == "well_test"
        self.memories[well].append(
            torch.tensor([x], dtype=DTYPE),
            torch.tensor([float(q_total)], dtype=DTYPE),
            torch.tensor([t], dtype=torch.int64),
            torch.tensor([well_test]),
            torch.zeros(1, len(FeatureTracker.names), dtype=DTYPE),
        )
        self.n_learned[well] = self.n_learned.get(well, 0) + 1
        if self.rounds:
            item = (j, x, float(q_total), t, well_test)
            day = t // DAY_NS
            late = self._day is not None and day < self._day
            if late and self._undo is not None and self._undo[0] == day:
                changed |= self._relearn_round(item)
            else:  # this day's round, or (later than one round) the round still open
                self._held.append(item)
        elif self.method.next_due() is None:
            # no history fit, so no calendar: it starts at the first measurement, and the first
            # retrain fits the field on what came until then (a fit on one measurement would
            # take the shared input normalisation from a single row)
            self.method.start(t)
        return changed

    def retrain(self, now: datetime | pd.Timestamp) -> None:
        """Retrain the whole field now on everything remembered up to ``now`` (e.g. after a
        confirmed drift on one of its wells); scheduled retrains count from ``now``."""
        ts = utc_timestamp(now)
        self._undo = None
        self.method.retrain(self, int(ts.value) + 1)
        self.method.start(int(ts.value))
        self._bump(ts.to_pydatetime(warn=False))

    def _bump(self, when: datetime) -> None:
        self.version += 1
        self.n_updates += 1
        self.last_update = when

    # -- checkpoints ------------------------------------------------------------------------------
    def checkpoint(self) -> bytes:
        """The whole field as bytes (tensors and plain values, no pickle)."""
        held = self._held
        payload = {
            "format": FIELD_CHECKPOINT_FORMAT,
            "model": self.model_name,
            "method": self.method_text,
            "train": json.dumps(self.train.__dict__),
            "online": json.dumps(self.online.__dict__),
            "model_kwargs": json.dumps(self.model_kwargs),
            "seed": self.seed,
            "wells": list(self.wells),
            "state": self.model.state_dict(),
            "method_state": self.method.state_dict(),
            "version": self.version,
            "n_updates": self.n_updates,
            "last_update": self.last_update.isoformat() if self.last_update else "",
            "day": -1 if self._day is None else int(self._day),
            "held": {
                "well": torch.tensor([h[0] for h in held], dtype=torch.int64),
                "x": torch.tensor([h[1] for h in held], dtype=DTYPE).reshape(len(held), 6),
                "y": torch.tensor([h[2] for h in held], dtype=DTYPE),
                "t": torch.tensor([h[3] for h in held], dtype=torch.int64),
                "w": torch.tensor([h[4] for h in held], dtype=torch.bool),
            },
            "n_learned": torch.tensor([self.n_learned.get(w, 0) for w in self.wells]),
            "memory": {w: self.memories[w].state() for w in self.wells},
        }
        buf = io.BytesIO()
        torch.save(payload, buf)
        return buf.getvalue()

    @classmethod
    def restore(cls, blob: bytes, *, train: TrainSettings | None = None) -> FieldLearner:
        """Rebuild a field from :meth:`checkpoint` bytes (``weights_only``: never runs code).

        ``train`` replaces the saved batch settings (e.g. the service's retrain budget)."""
        try:
            p = torch.load(io.BytesIO(blob), weights_only=True)
        except Exception as exc:
            raise ConfigError(f"The field checkpoint cannot be read: {exc}") from None
        if not isinstance(p, dict) or p.get("format") != FIELD_CHECKPOINT_FORMAT:
            raise ConfigError(
                f"The checkpoint is not a VFM field-learner checkpoint ({FIELD_CHECKPOINT_FORMAT})."
            )
        saved_train = replace(TrainSettings(), **json.loads(p["train"]))
        field = cls(
            p["model"],
            p["method"],
            wells=list(p["wells"]),
            train=train or saved_train,
            online=replace(OnlineSettings(), **json.loads(p["online"])),
            model_kwargs=json.loads(p["model_kwargs"]),
            seed=int(p["seed"]),
        )
        field.model.load_state_dict(p["state"])
        field.method.load_state_dict(p["method_state"])
        field.version = int(p["version"])
        field.n_updates = int(p["n_updates"])
        field.last_update = datetime.fromisoformat(p["last_update"]) if p["last_update"] else None
        field._day = None if int(p["day"]) < 0 else int(p["day"])
        h = p["held"]
        field._held = [
            (int(j), [float(v) for v in x], float(y), int(t), bool(w))
            for j, x, y, t, w in zip(
                h["well"].tolist(),
                h["x"].tolist(),
                h["y"].tolist(),
                h["t"].tolist(),
                h["w"].tolist(),
                strict=True,
            )
        ]
        for w, n in zip(field.wells, p["n_learned"].tolist(), strict=True):
            field.n_learned[w] = int(n)
            field.memories[w].load(p["memory"][w])
        return field


class FieldWell:
    """One well of a :class:`FieldLearner`, with the surface of :class:`WellLearner` the
    service uses. Its version is the field's: a step of the shared model changes every
    well's predictions."""

    def __init__(self, field: FieldLearner, well: str) -> None:
        self.field = field
        self.well = well

    # -- what it is -------------------------------------------------------------------------------
    @property
    def model_name(self) -> str:
        return self.field.model_name

    @property
    def name(self) -> str:
        return self.field.name

    @property
    def model(self) -> ChokeModel:
        return self.field.model

    @property
    def method(self) -> LearningMethod:
        return self.field.method

    @property
    def effects(self) -> list[str]:
        return []

    @property
    def train(self) -> TrainSettings:
        return self.field.train

    @train.setter
    def train(self, value: TrainSettings) -> None:
        self.field.train = value

    @property
    def online(self) -> OnlineSettings:
        return self.field.online

    @property
    def model_kwargs(self) -> dict[str, Any]:
        return self.field.model_kwargs

    @property
    def seed(self) -> int:
        return self.field.seed

    @property
    def version(self) -> int:
        return self.field.version

    @property
    def n_updates(self) -> int:
        return self.field.n_updates

    @property
    def last_update(self) -> datetime | None:
        return self.field.last_update

    @property
    def memory(self) -> WellMemory:
        return self.field.memories[self.well]

    @property
    def remembered(self) -> int:
        return len(self.memory)

    @property
    def ready(self) -> bool:
        return self.field.is_ready(self.well)

    # -- what it can do (see vfm_core.learning.streaming.protocol.Learner) ----------------------------------
    #: the field's network is shared: a step for this well changes every well's predictions
    shares_model = True
    #: its predictions and updates go through the field, never through a shared model call
    predicts_in_groups = False
    learns_in_groups = False

    @property
    def checkpoint_group(self) -> FieldLearner:
        """The field: this well's checkpoint is the field's snapshot, which serves every well."""
        return self.field

    def renumber(self, at_least: int) -> None:
        """Refused: the version is the field's, moved by every well's steps."""
        raise ConfigError(
            f"Well {self.well} is served by the field-wide model {self.name}, whose version is "
            "the whole field's; it cannot be renumbered for one well."
        )

    def remember_at_most(self, rows: int | None) -> None:
        """Nothing: the field keeps every well's measurements (its retrains refit the whole
        field on them, and its snapshot holds them); the bound is a per-well learner's."""

    def deferred_note(self) -> str:
        """A per-measurement method learns with the field's day round; ``pbl`` at its retrain."""
        if self.field.method.per_measurement:
            return (
                "Stored; the field-wide model learns it with the other wells' measurements of "
                "its day when the day ends."
            )
        return (
            "Stored; the model keeps it for its next periodic retrain "
            f"(method {self.field.method.text})."
        )

    def fit_history(self, *args: Any, **kwargs: Any) -> None:
        """Refused: the field is fitted as a whole (:meth:`FieldLearner.fit_history`)."""
        raise ConfigError(self._fitted_with_field())

    def adopt_fit(self, *args: Any, **kwargs: Any) -> None:
        """Refused: the field is fitted as a whole (:meth:`FieldLearner.fit_history`)."""
        raise ConfigError(self._fitted_with_field())

    def _fitted_with_field(self) -> str:
        return (
            f"Well {self.well} is served by the field-wide model {self.name}, which is fitted "
            "on every well's history at once (FieldLearner.fit_history), not one well at a time."
        )

    # -- streaming ---------------------------------------------------------------------------------
    def predict(
        self, inputs: Sequence[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        return self.field.predict(self.well, inputs, when)

    def predict_block(self, inputs: np.ndarray, times_ns: np.ndarray) -> dict[str, np.ndarray]:
        """Refused (ValueError): a well of the field is predicted sample by sample, since the
        field's clock (its day rounds, its retrains) moves with every sample of any well."""
        raise ValueError(
            f"predict_block is not available for {self.well}, a well of the field-wide model "
            f"{self.name}: its samples are predicted one by one."
        )

    def learn(
        self,
        inputs: Sequence[float] | torch.Tensor,
        q_total: float,
        when: datetime | pd.Timestamp,
        source: str = "mpfm",
    ) -> bool:
        return self.field.learn(self.well, inputs, q_total, when, source)

    def retrain(self, now: datetime | pd.Timestamp) -> None:
        self.field.retrain(now)

    def physical_parameters(self) -> dict[str, dict[str, Any]]:
        """Named physical parameters: none for a shared network (``mtl``)."""
        return {}

    def refit_as(self, *args: Any, **kwargs: Any) -> Any:
        raise ConfigError(
            f"Well {self.well} is served by the field-wide model {self.name}, whose network is "
            "shared with the other wells; its model cannot be changed alone. Change model.name "
            "in the config (it applies to every well) and restart."
        )

    def checkpoint(self) -> bytes:
        """The whole field's checkpoint (see :meth:`FieldLearner.checkpoint`)."""
        return self.field.checkpoint()


if TYPE_CHECKING:  # a FieldWell keeps the Learner protocol (mypy checks the assignment)
    _KEEPS_PROTOCOL: type[Learner] = FieldWell


# -- helpers ---------------------------------------------------------------------------------------
def _pack(
    wells: Sequence[str],
    rows: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]],
    extra_columns: Sequence[str],
) -> Batch:
    """Per-well rows (inputs, rates, times, well tests) as a left-aligned padded batch,
    laid out as :func:`vfm_core.data.make_batch` lays out a frame's rows."""
    n_w = len(wells)
    counts = [int(r[1].shape[0]) for r in rows]
    n = max(counts, default=0)
    x = torch.zeros(n_w, n, 6, dtype=DTYPE)
    y = torch.zeros(n_w, n, dtype=DTYPE)
    mask = torch.zeros(n_w, n, dtype=torch.bool)
    t = torch.full((n_w, n), NEVER, dtype=torch.int64)
    wt = torch.zeros(n_w, n, dtype=torch.bool)
    for j, (xj, yj, tj, wj) in enumerate(rows):
        c = counts[j]
        pad = xj[0] if c else torch.tensor(_PAD, dtype=DTYPE)
        x[j] = pad
        if c:
            x[j, :c] = xj
            y[j, :c] = yj
            mask[j, :c] = True
            t[j, :c] = tj
            wt[j, :c] = wj
    return Batch(
        list(wells),
        x,
        y,
        mask,
        t,
        torch.full((n_w, n), -1, dtype=torch.int64),
        wt,
        torch.zeros(n_w, n, len(extra_columns), dtype=DTYPE),
        tuple(extra_columns),
    )


def _grown(old: Mapping[str, Any], fresh: Mapping[str, Any], old_n: int) -> dict[str, Any]:
    """A state dict for more wells: the fresh one with the old wells' rows and every
    shared tensor taken from ``old``."""
    out: dict[str, Any] = {}
    for key, new in fresh.items():
        value = old.get(key)
        if isinstance(new, Mapping) and isinstance(value, Mapping):
            out[key] = _grown(value, new, old_n)
        elif isinstance(new, torch.Tensor) and isinstance(value, torch.Tensor):
            if value.shape == new.shape:
                out[key] = value.clone()
            elif (
                value.dim() >= 1
                and value.shape[0] == old_n
                and new.shape[0] > old_n
                and value.shape[1:] == new.shape[1:]
            ):
                grown = new.clone()
                grown[:old_n] = value
                out[key] = grown
            else:  # pragma: no cover - a state that is not stacked by well
                raise ConfigError(
                    f"The state '{key}' {tuple(value.shape)} does not grow by well; this model "
                    "cannot take new wells while it runs."
                )
        else:
            out[key] = copy.deepcopy(value if value is not None else new)
    return out


def _per_well_indices(model: ChokeModel) -> set[int]:
    """Positions of the model's per-well parameters among its trained ones (an optimiser's order)."""
    ids = {id(p) for p in model.per_well_parameters()}
    trained = [p for p in model.parameters() if p.requires_grad]
    return {i for i, p in enumerate(trained) if id(p) in ids}


def _grown_method(
    old: dict[str, Any], fresh: dict[str, Any], old_n: int, new_n: int, per_well: set[int]
) -> dict[str, Any]:
    """A method's state for more wells: the old wells keep theirs, a new well starts as
    the method binds it, but on the field's calendar and iteration count (in the study
    every well of the field is there from the start, with both)."""
    opt = old.get("optimizer")
    state = _grown(
        {k: v for k, v in old.items() if k != "optimizer"},
        {k: v for k, v in fresh.items() if k != "optimizer"},
        old_n,
    )
    if "optimizer" in old or "optimizer" in fresh:
        state["optimizer"] = _grown_optimizer(opt, old_n, new_n, per_well) if opt else {}
    its = old.get("iterations")
    if isinstance(its, torch.Tensor) and its.numel():
        state["iterations"][old_n:] = int(its.max())
    nxt = old.get("next")
    if isinstance(nxt, torch.Tensor) and nxt.numel():
        state["next"][old_n:] = int(nxt.min())
    return state


def _grown_optimizer(
    opt: dict[str, Any], old_n: int, new_n: int, per_well: set[int]
) -> dict[str, Any]:
    """An optimiser's state for more wells: a new well's moments start at zero (as a well
    that has not been learned from yet has them)."""
    out = copy.deepcopy(opt)
    for idx, entry in out.get("state", {}).items():
        if int(idx) not in per_well:
            continue
        for key, value in list(entry.items()):
            if isinstance(value, torch.Tensor) and value.dim() >= 1 and value.shape[0] == old_n:
                pad = torch.zeros((new_n - old_n, *value.shape[1:]), dtype=value.dtype)
                entry[key] = torch.cat([value, pad])
    return out
