"""One well's model and learning method, fed one sample at a time: the core of the service.

:class:`WellLearner` wraps a per-well model (any registered model but the field-wide
``mtl``) with its learning method. ``predict`` answers a sensor sample with rates;
``learn`` takes a measured rate paired with the sample's inputs and either updates at
once (``ol``) or keeps it for the next periodic retrain (``pbl:<period>``). The same
models and update code as :func:`vfm_core.study.run_prequential` run here, so a replay
through the service reproduces ``vfm evaluate``.

State is tensors and plain values only: :meth:`WellLearner.checkpoint` returns bytes
that :meth:`WellLearner.restore` reads back with ``torch.load(weights_only=True)``.
"""

from __future__ import annotations

import io
import json
from dataclasses import replace
from datetime import datetime
from typing import Any

import pandas as pd
import torch

from vfm_core import physics as ph
from vfm_core.data import DTYPE, Batch
from vfm_core.errors import ConfigError
from vfm_core.learners import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    Method,
    OnlineLearner,
    OnlineSettings,
    TrainSettings,
    fit_batch,
    parse_method,
)
from vfm_core.models import MODELS, ChokeModel, make_model

__all__ = ["WellLearner", "phase_split", "PARAMETER_UNITS"]

PARAMETER_UNITS: dict[str, str] = {name: p.unit for name, p in ph.PRIORS.items()} | {"a_max": "m2"}

_INT64_MAX = torch.iinfo(torch.int64).max


def phase_split(
    q_total: torch.Tensor, x: torch.Tensor, theta: dict[str, torch.Tensor] | None = None
) -> dict[str, torch.Tensor]:
    """Split total rates (Sm3/h) into gas, oil and water by the inputs' mass fractions.

    Q = mdot (eta_g/rho_g,sc + eta_o/rho_o + eta_w/rho_w), so each phase's share of Q is
    its term over the sum. Densities from ``theta`` (a mechanistic model's learned values)
    or the prior means.
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


def _utc(when: datetime | pd.Timestamp) -> pd.Timestamp:
    ts = pd.Timestamp(when)
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


def _single(
    x: list[float] | torch.Tensor, y: float = 0.0, t_ns: int = 0, valid: bool = True
) -> Batch:
    xt = torch.as_tensor(x, dtype=DTYPE).reshape(1, 1, 6)
    return Batch(
        ["well"],
        xt,
        torch.tensor([[y]], dtype=DTYPE),
        torch.tensor([[valid]]),
        torch.tensor([[t_ns]], dtype=torch.int64),
        torch.tensor([[0]], dtype=torch.int64),
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
    ) -> None:
        if model not in MODELS:
            raise ConfigError(f"Unknown model '{model}'; choose one of {', '.join(MODELS)}.")
        if MODELS[model].shared:
            raise ConfigError(
                f"Model '{model}' shares parameters across the whole field and cannot run per well "
                "in the service; use it with `vfm evaluate`, or choose a per-well model."
            )
        self.well = well
        self.model_name = model
        self.method: Method = parse_method(method)
        self.train = train or DEFAULT_TRAIN[model]
        self.online = online or DEFAULT_ONLINE[model]
        self.model_kwargs = dict(model_kwargs or {})
        self.seed = seed
        self.model: ChokeModel = make_model(model, [well], seed=seed, **self.model_kwargs)
        self._online = OnlineLearner(self.model, self.online)
        self.version = 0
        self.n_updates = 0
        self.last_update: datetime | None = None
        self.iterations = torch.tensor([self.train.default_iter], dtype=torch.int64)
        self.next_retrain: pd.Timestamp | None = None
        # everything learned from, for periodic retrains: inputs, rates, times (ns)
        self._x = torch.empty(0, 6, dtype=DTYPE)
        self._y = torch.empty(0, dtype=DTYPE)
        self._t = torch.empty(0, dtype=torch.int64)

    # -- history --------------------------------------------------------------------------
    def fit_history(self, x: torch.Tensor, y: torch.Tensor, time_ns: torch.Tensor) -> None:
        """Initial MAP fit on a well's history: inputs [N, 6], rates [N] Sm3/h, times [N] ns."""
        n = int(x.shape[0])
        if n == 0:
            return
        batch = Batch(
            [self.well],
            x.reshape(1, n, 6).to(DTYPE),
            y.reshape(1, n).to(DTYPE),
            torch.ones(1, n, dtype=torch.bool),
            time_ns.reshape(1, n),
            torch.arange(n).reshape(1, n),
        )
        summary = fit_batch(self.model, batch, self.train)
        self.adopt_fit(x, y, time_ns, summary["iterations"])

    def adopt_fit(
        self,
        x: torch.Tensor,
        y: torch.Tensor,
        time_ns: torch.Tensor,
        iterations: torch.Tensor,
        first_retrain_base: datetime | None = None,
    ) -> None:
        """Take on an initial fit done elsewhere (e.g. one batched fit of the whole field).

        The model's parameters must already hold the fit; this records the history it was
        fitted on, the early-stopped iteration count for later retrains, and (``pbl``) the
        retrain calendar: one period after ``first_retrain_base`` (e.g. the split, as
        ``vfm evaluate`` counts) or after the last history row.
        """
        self.iterations = iterations.clone()
        self._remember(x, y, time_ns)
        last = pd.Timestamp(int(time_ns.max()), tz="UTC")
        self._bump(last.to_pydatetime())
        if self.method.kind == "pbl":
            assert self.method.period is not None
            base = last if first_retrain_base is None else _utc(first_retrain_base)
            self.next_retrain = base + self.method.period

    def _remember(self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor) -> None:
        self._x = torch.cat([self._x, x.reshape(-1, 6).to(DTYPE)])
        self._y = torch.cat([self._y, y.reshape(-1).to(DTYPE)])
        self._t = torch.cat([self._t, t.reshape(-1)])

    def _bump(self, when: datetime) -> None:
        self.version += 1
        self.n_updates += 1
        self.last_update = when

    # -- streaming ------------------------------------------------------------------------
    @property
    def ready(self) -> bool:
        """True once the model has seen enough data to predict (priors alone give no scale)."""
        return bool(self.model.ready[0])

    def predict(
        self, inputs: list[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        """Rates (Sm3/h) for one sample's inputs; all None until the model is ready.

        With ``pbl``, a sample time ``when`` past the next retrain time retrains first
        (on everything learned before that time), so the calendar of retrains matches
        ``vfm evaluate``.
        """
        if when is not None:
            self._retrain_due(_utc(when))
        if not self.ready:
            return {"q_total": None, "q_gas": None, "q_oil": None, "q_water": None}
        x = torch.as_tensor(inputs, dtype=DTYPE).reshape(1, 1, 6)
        q = self.model.predict(x)
        theta = None
        params = self.model.physical_parameters()
        if params:
            theta = {k: v[0] for k, v in params.items() if k in ph.PRIORS}
        phases = phase_split(q, x, theta)
        out: dict[str, float | None] = {"q_total": float(q[0, 0])}
        out.update({k: float(v[0, 0]) for k, v in phases.items()})
        return out

    def learn(self, inputs: list[float] | torch.Tensor, q_total: float, when: datetime) -> bool:
        """Learn from one measured rate (Sm3/h) paired with the inputs at its time.

        ``ol`` updates now; ``pbl`` stores it for the next periodic retrain (retraining
        first if a retrain time has passed). Returns True when the model changed.
        """
        ts = _utc(when)
        changed = self._retrain_due(ts)
        x = torch.as_tensor(inputs, dtype=DTYPE).reshape(1, 6)
        y = torch.tensor([float(q_total)], dtype=DTYPE)
        t = torch.tensor([ts.value], dtype=torch.int64)
        self._remember(x, y, t)
        if self.method.kind == "ol":
            self._online.learn(_single(x, float(q_total), ts.value))
            self._bump(ts.to_pydatetime())
            return True
        assert self.method.period is not None
        if not self.ready:  # priors only: fit on the first data so predictions can start
            self._retrain(ts + pd.Timedelta(1, "ns"))
            self.next_retrain = ts + self.method.period
            return True
        if self.next_retrain is None:
            self.next_retrain = ts + self.method.period
        return changed

    def retrain(self, now: datetime | pd.Timestamp) -> None:
        """Retrain now on everything learned up to ``now`` (e.g. after a confirmed drift)."""
        ts = _utc(now)
        self._retrain(ts + pd.Timedelta(1, "ns"))
        if self.method.kind == "pbl" and self.method.period is not None:
            self.next_retrain = ts + self.method.period

    def _retrain_due(self, now: pd.Timestamp) -> bool:
        """Run every periodic retrain whose time has come (pbl only)."""
        changed = False
        if self.method.kind != "pbl" or self.next_retrain is None or not self.ready:
            return changed
        assert self.method.period is not None
        while self.next_retrain <= now:
            self._retrain(self.next_retrain)
            self.next_retrain += self.method.period
            changed = True
        return changed

    def _retrain(self, until: pd.Timestamp) -> None:
        """Batch retrain on everything learned before ``until`` (or the window), warm start."""
        keep = self._t < until.value
        if self.method.window is not None:
            keep &= self._t >= (until - self.method.window).value
        x, y, t = self._x[keep], self._y[keep], self._t[keep]
        n = int(x.shape[0])
        if n == 0:
            return
        batch = Batch(
            [self.well],
            x.reshape(1, n, 6),
            y.reshape(1, n),
            torch.ones(1, n, dtype=torch.bool),
            t.reshape(1, n),
            torch.arange(n).reshape(1, n),
        )
        if not self.ready:
            summary = fit_batch(self.model, batch, self.train)
            self.iterations = summary["iterations"]
        else:
            fit_batch(self.model, batch, self.train, self.iterations)
        self._bump(until.to_pydatetime(warn=False))

    # -- state ----------------------------------------------------------------------------
    def physical_parameters(self) -> dict[str, dict[str, float | str]]:
        """Named physical parameters with values (SI) and units."""
        return {
            name: {"value": float(v[0]), "unit": PARAMETER_UNITS.get(name, "")}
            for name, v in self.model.physical_parameters().items()
        }

    def checkpoint(self) -> bytes:
        """Everything needed to resume, as bytes (tensors and plain values, no pickle)."""
        payload = {
            "format": "vfm-well-learner/1",
            "well": self.well,
            "model": self.model_name,
            "method": self.method.text,
            "train": json.dumps(self.train.__dict__),
            "online": json.dumps(self.online.__dict__),
            "model_kwargs": json.dumps(self.model_kwargs),
            "seed": self.seed,
            "state": self.model.state_dict(),
            "optimizer": self._online._opt.state_dict() if self._online._opt is not None else {},
            "version": self.version,
            "n_updates": self.n_updates,
            "last_update": self.last_update.isoformat() if self.last_update else "",
            "next_retrain": self.next_retrain.isoformat() if self.next_retrain is not None else "",
            "iterations": self.iterations,
            "x": self._x,
            "y": self._y,
            "t": self._t,
        }
        buf = io.BytesIO()
        torch.save(payload, buf)
        return buf.getvalue()

    @classmethod
    def restore(cls, blob: bytes) -> WellLearner:
        """Rebuild a learner from :meth:`checkpoint` bytes (``weights_only``: never runs code)."""
        try:
            p = torch.load(io.BytesIO(blob), weights_only=True)
        except Exception as exc:
            raise ConfigError(f"The checkpoint cannot be read: {exc}") from None
        if not isinstance(p, dict) or p.get("format") != "vfm-well-learner/1":
            raise ConfigError(
                "The checkpoint is not a VFM well-learner checkpoint (vfm-well-learner/1)."
            )
        learner = cls(
            p["well"],
            p["model"],
            p["method"],
            train=replace(TrainSettings(), **json.loads(p["train"])),
            online=replace(OnlineSettings(), **json.loads(p["online"])),
            model_kwargs=json.loads(p["model_kwargs"]),
            seed=int(p["seed"]),
        )
        learner.model.load_state_dict(p["state"])
        if p["optimizer"]:
            params = [q for q in learner.model.parameters() if q.requires_grad]
            learner._online._opt, learner._online._sched = _make_opt(params, learner.online)
            learner._online._opt.load_state_dict(p["optimizer"])
        learner.version = int(p["version"])
        learner.n_updates = int(p["n_updates"])
        learner.last_update = datetime.fromisoformat(p["last_update"]) if p["last_update"] else None
        learner.next_retrain = pd.Timestamp(p["next_retrain"]) if p["next_retrain"] else None
        learner.iterations = p["iterations"]
        learner._x, learner._y, learner._t = p["x"], p["y"], p["t"]
        return learner


def _make_opt(params: list[torch.nn.Parameter], s: OnlineSettings) -> tuple[Any, Any]:
    from vfm_core.learners import _optimizer

    return _optimizer(params, s.optimizer, s.lr, s.schedule_power)
