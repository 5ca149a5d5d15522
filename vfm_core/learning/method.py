"""The learning-method protocol: how a fitted model keeps learning from new measurements.

One protocol, implemented once per method, used alike by the prequential study
(:func:`vfm_core.jobs.study.run_prequential`, all wells at once), the streaming learner
(:class:`vfm_core.learning.streaming.WellLearner`, one well) and therefore the service. A method
object holds the method's hyperparameters (parsed from its text, ``pbl:14d``) and, once
bound to a model, its learned state; the model's parameters stay in the model.

Life of a method, for a model of W wells::

    method = parse_method("pbl:14d").bind(model, train=..., online=...)
    method.fit(history_batch)          # initial MAP fit (or adopt(batch, iterations))
    method.start(split_ns)             # the calendar origin of scheduled retrains
    loop, in time order:
        method.retrain_due(memory, now_ns)    # scheduled retrains whose time has come
        forecast = method.predict(batch)      # mean rate and, if the method has one, sd
        method.on_measurement(batch)          # learn from the measurement(s)

- ``per_measurement``: True when the method learns from each measurement (``ol``,
  ``pbl:auto``'s drift test, ``bayes``). A method that learns only at scheduled retrains
  (``pbl``) may have its predictions between two retrains made in one call; the study
  does that and tells it of measurements only through ``retrain_due``.
- ``next_due()``: when the next scheduled retrain falls due (epoch ns), or None.
- ``intervals``: True when ``predict`` gives a predictive standard deviation.
- ``streaming``: False for a method the streaming learner (and so the service) does not
  run; ``pbl:auto`` is one: the service has its own drift test (``drift.on_drift``).
- ``state_dict()`` / ``load_state_dict()``: tensors and plain values only (checkpoints
  are read back with ``torch.load(weights_only=True)``).
- Many wells at once (the service holds one method per well, each on a one-well model):
  ``group_key()`` / ``predict_group(methods, batch)`` and ``learn_key()`` /
  ``learn_group(methods, batches, memories)``, as river's mini-batch estimators add
  ``predict_many`` / ``learn_many``. Each method stacks its own calls (``ol`` and
  ``bayes`` in their modules, the models through :mod:`vfm_core.learning.stacking`); the
  defaults predict with the stacked models and learn one well at a time, so a new method
  is correct without them (:func:`vfm_core.learning.streaming.predict_many`,
  :func:`vfm_core.learning.streaming.learn_many`).

Methods register with :func:`register`; :func:`parse_method` finds a method by the start
of its text and lists the valid ones for an unknown text. A new method is a subclass in
its own module, registered and imported by :mod:`vfm_core.learning`; nothing else changes.
"""

from __future__ import annotations

import copy
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Sequence
from dataclasses import replace
from typing import Any, ClassVar, NamedTuple, TypeVar

import pandas as pd
import torch

from vfm_core.data import Batch
from vfm_core.errors import ConfigError
from vfm_core.learning.kernels import predict_rates
from vfm_core.learning.memory import Memory
from vfm_core.learning.stacking import stacked_rates
from vfm_core.learning.training import TrainSettings, fit_batch, train_defaults
from vfm_core.models import ChokeModel

__all__ = [
    "Forecast",
    "LearningMethod",
    "METHODS",
    "register",
    "parse_method",
    "parse_span",
    "parse_options",
    "NEVER",
    "ready_for_group",
]

#: "no time yet": later than every int64 nanosecond time
NEVER = torch.iinfo(torch.int64).max


class Forecast(NamedTuple):
    """A prediction [W, N], Sm3/h: the rate and, for methods with ``intervals``, its
    predictive standard deviation and the bounds of its central 90 % interval (else None).

    The interval is that of the measurement being predicted (the sample's source: MPFM or
    well test), parameter uncertainty and that meter's noise together."""

    mean: torch.Tensor
    std: torch.Tensor | None = None
    p05: torch.Tensor | None = None
    p95: torch.Tensor | None = None


def parse_span(text: str, what: str, method: str) -> pd.Timedelta:
    """A positive time span like ``14d``, ``182d`` or ``12h``; a clear error otherwise."""
    # pandas deprecates the lower-case day unit; accept "14d" as users write it
    normalised = re.sub(r"(?<=\d)d\b", "D", text.strip())
    try:
        span = pd.Timedelta(normalised)
    except ValueError:
        span = None
    if span is None or pd.isna(span) or span <= pd.Timedelta(0):
        raise ConfigError(
            f"Method '{method}': the {what} '{text}' is not a positive time span; "
            "write it like 14d, 182d or 12h."
        )
    return span


def parse_options(
    text: str, rest: str, casters: dict[str, Callable[[str], Any]], example: str
) -> dict[str, Any]:
    """``key=value`` options separated by ':' (``rest`` is the text after the method's name)."""
    options: dict[str, Any] = {}
    for part in [p for p in rest.split(":") if p]:
        key, _, value = part.partition("=")
        caster = casters.get(key)
        if caster is None or not value:
            known = ", ".join(f"{k}=" for k in casters) or "no options"
            raise ConfigError(
                f"Method '{text}': unknown option '{part}'; it takes {known} (e.g. {example})."
            )
        try:
            options[key] = caster(value)
        except (ValueError, ConfigError) as exc:
            detail = str(exc) if isinstance(exc, ConfigError) else f"'{value}' is not a valid {key}"
            raise ConfigError(f"Method '{text}': {detail.rstrip('.')}.") from None
    return options


M = TypeVar("M", bound="LearningMethod")


class LearningMethod(ABC):
    """Base of every learning method; see the module docstring for the protocol.

    Subclasses set the class variables, parse their text in :meth:`from_text`, and
    override :meth:`_learn` (per-measurement learning), :meth:`next_due` /
    :meth:`retrain_due` (scheduled retrains), :meth:`predict` (intervals) and the state.
    """

    #: the registry name and the start of the method's text (``ol``, ``pbl``, ``pbl:auto``)
    key: ClassVar[str] = ""
    #: the method family, as ``vfm tune`` and the reports group them (``ol``, ``pbl``, ...)
    kind: ClassVar[str] = ""
    #: one line for listings and errors
    summary: ClassVar[str] = ""
    #: a valid text of the method (the contract tests run it)
    example: ClassVar[str] = ""
    per_measurement: ClassVar[bool] = True
    intervals: ClassVar[bool] = False
    streaming: ClassVar[bool] = True

    def __init__(self, text: str, *, window: pd.Timedelta | None = None) -> None:
        self.text = text
        #: retrains use only the measurements of this span before the retrain time
        self.window = window
        self._model: ChokeModel | None = None
        self.train = TrainSettings()
        #: iterations per well of the initial (early-stopped) fit, reused by warm retrains
        self.iterations = torch.zeros(0, dtype=torch.int64)
        #: per well, how many measurements that count was chosen on (0: none, the default);
        #: a retrain chooses it again once the well holds RECHOOSE_GROWTH times as many
        self.chosen_on = torch.zeros(0, dtype=torch.int64)
        #: the model's state right after the initial MAP fit (set by :meth:`fit`, before
        #: :meth:`_fitted`), for a study to share with the other methods; None otherwise
        self.fit_state: dict[str, torch.Tensor] | None = None
        #: times (epoch ns) of the retrains so far in the order they ran (a checkpoint keeps
        #: the last 100), and their count
        self.retrains: list[int] = []
        self.n_retrains = 0

    @classmethod
    def from_text(cls: type[M], text: str) -> M:
        """The method described by ``text`` (its key, then ``:option=value`` parts)."""
        rest = text[len(cls.key) :].lstrip(":")
        if rest:
            parse_options(text, rest, {}, cls.key)
        return cls(text)

    def __str__(self) -> str:
        return self.text

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.text!r})"

    @property
    def couples_wells(self) -> bool:
        """True when a well's forecasts depend on the other wells' measurements through the
        method (not the model): a study must then replay the field in time order, as a
        service sees it. False by default."""
        return False

    def coupling_samples(self, batch: Batch) -> torch.Tensor | None:
        """For a method that :attr:`couples_wells`: the samples of ``batch`` [W, N] whose
        learning changes what the other wells' forecasts read (a study replays in time
        order around them only); None: every sample."""
        return None

    # -- binding ---------------------------------------------------------------------------
    @property
    def model(self) -> ChokeModel:
        if self._model is None:
            raise RuntimeError(f"The method {self.text} is not bound to a model; call bind().")
        return self._model

    def bind(self: M, model: ChokeModel, *, train: TrainSettings | None = None, **_: Any) -> M:
        """Attach the method to ``model`` (its parameters are what the method learns).

        ``train`` sets the batch fits (initial and retrains); subclasses take their own
        settings as further keywords (``online`` for ``ol``) and ignore the others.
        """
        self._model = model
        self.train = train or train_defaults(model)
        self.iterations = torch.full(
            (len(model.wells),), self.train.default_iter, dtype=torch.int64
        )
        self.chosen_on = torch.zeros(len(model.wells), dtype=torch.int64)
        return self

    def copy_for(self: M, model: ChokeModel) -> M:
        """The same method with the same state, bound to ``model`` (a copy of the bound one)."""
        other = copy.copy(self)
        other._model = model
        other._rebind(model)
        other.load_state_dict(copy.deepcopy(self.state_dict()))
        return other

    def _rebind(self, model: ChokeModel) -> None:
        """Rebuild what holds references to the model's parameters (optimisers)."""
        return None

    # -- fitting ---------------------------------------------------------------------------
    def fit(self, batch: Batch, *, converge: bool = False) -> None:
        """Initial MAP fit of the model on ``batch`` (``converge``: no early stopping)."""
        settings = replace(self.train, early_stopping=False) if converge else self.train
        summary = fit_batch(self.model, batch, settings)
        self.iterations = summary["iterations"].clone()
        self.chosen_on = batch.count().clone()
        # the MAP fit itself, before :meth:`_fitted` (a filter's Kalman pass moves the
        # parameters): what another method of a study adopts (vfm_core.jobs.study._initial_fit)
        self.fit_state = {k: v.detach().clone() for k, v in self.model.state_dict().items()}
        self._fitted(batch, torch.ones(batch.n_wells, dtype=torch.bool))

    def adopt(self, batch: Batch, iterations: torch.Tensor) -> None:
        """Take on an initial fit done elsewhere (the model already holds it)."""
        self.iterations = iterations.clone()
        self.chosen_on = batch.count().clone()
        self._fitted(batch, torch.ones(batch.n_wells, dtype=torch.bool))

    def chose(self, wells: torch.Tensor, iterations: torch.Tensor, counts: torch.Tensor) -> None:
        """Record a new early-stopped iteration count for ``wells`` [W] (bool), chosen on
        ``counts`` [W] measurements."""
        self.iterations = torch.where(wells, iterations, self.iterations)
        self.chosen_on = torch.where(wells, counts, self.chosen_on)

    def _fitted(self, batch: Batch, wells: torch.Tensor) -> None:
        """Hook after a batch fit of ``wells`` on ``batch`` (Bayesian methods take their
        covariance here)."""
        return None

    def start(self, t_ns: int) -> None:
        """The calendar origin of scheduled retrains (the split, or the last history row)."""
        return None

    # -- scheduled retrains -----------------------------------------------------------------
    def next_due(self) -> int | None:
        """When the next scheduled retrain of any well falls due (epoch ns), or None."""
        return None

    def retrain_due(self, memory: Memory, now_ns: torch.Tensor) -> torch.Tensor:
        """Run every scheduled retrain due at or before ``now_ns`` [W] (epoch ns; NEVER for
        a well with nothing now). Returns the wells whose model changed [W] (bool)."""
        return torch.zeros(len(self.model.wells), dtype=torch.bool)

    def retrain(
        self,
        memory: Memory,
        until_ns: int,
        wells: torch.Tensor | None = None,
        at_ns: int | None = None,
    ) -> None:
        """Warm-start batch retrain of ``wells`` (default all) on the memory before ``until_ns``
        (the method's window applies), recorded as done at ``at_ns`` (default ``until_ns``).
        A gradient-free model does not retrain."""
        model = self.model
        if model.gradient_free:
            return
        window = None if self.window is None else int(self.window.value)
        batch = memory.batch(until_ns, window)
        if not bool(batch.count().any()):
            return
        # a count chosen on a young well's few measurements (early stopping may pick one
        # step there) is chosen again, as the paper's batch learning does, once the well
        # holds RECHOOSE_GROWTH times the measurements it was chosen on
        counts = batch.count()
        if model.shared:  # one count for the field, chosen on the field's measurements
            grown = bool(counts.sum() >= RECHOOSE_GROWTH * self.chosen_on.sum())
            again = (counts > 0) & grown
        else:
            again = (counts > 0) & (counts >= RECHOOSE_GROWTH * self.chosen_on)
        if wells is not None:
            again &= wells
        summary = fit_batch(model, batch, self.train, self.iterations, wells=wells, rechoose=again)
        searched = summary.get("searched")
        if searched is not None and bool(searched.any()):  # too few to hold out: next time
            self.chose(searched, summary["chosen"], counts)
        self.retrains.append(int(until_ns if at_ns is None else at_ns))
        self.n_retrains += 1
        mask = torch.ones(batch.n_wells, dtype=torch.bool) if wells is None else wells
        self._fitted(batch, mask & (batch.count() > 0))

    # -- measurements and predictions -----------------------------------------------------------
    def on_measurement(self, batch: Batch, memory: Memory | None = None) -> torch.Tensor:
        """Learn from new measurements (normally one per well; wells without one are masked
        out and do not move). ``memory`` holds every measurement so far, these included.
        Returns the wells whose model changed [W] (bool)."""
        if self.model.gradient_free:  # the benchmark remembers the last value, whatever the method
            self.model.setup(batch)
            self.model.observe(batch)
            return batch.count() > 0
        return self._learn(batch, memory)

    @abstractmethod
    def _learn(self, batch: Batch, memory: Memory | None) -> torch.Tensor:
        """The method's own learning from measurements (gradient models); changed wells [W]."""

    def predict(self, batch: Batch) -> Forecast:
        """The predicted rate for every sample of ``batch`` (NaN where a well has no model)."""
        return Forecast(predict_rates(self.model, batch), None)

    # -- many wells at once ----------------------------------------------------------------------
    # A service holds one method per well, each bound to its own one-well model. Methods whose
    # group keys are equal may be asked for many wells' predictions, or updates, in one call
    # (as river's mini-batch estimators add ``predict_many`` / ``learn_many``); each method
    # decides how its own calls stack. The answers equal the one-by-one answers (to
    # rounding, 1e-12 relative), and so does every state they leave.

    def group_key(self) -> Hashable | None:
        """What methods (each bound to a one-well model) must share for :meth:`predict_group`
        to predict their wells in one call; None: never grouped. The default: a method that
        predicts with its model alone groups with every such method on a model of the same
        specification (:meth:`~vfm_core.models.base.ChokeModel.stack_key`)."""
        if type(self).predict is not LearningMethod.predict:  # its own predict: alone
            return None
        return ("model", self.model.stack_key())

    @classmethod
    def predict_group(cls, methods: Sequence[LearningMethod], batch: Batch) -> Forecast:
        """:meth:`predict` of K methods with equal :meth:`group_key`, row k of ``batch`` (a
        K-well batch) for ``methods[k]``; the forecast [K, N]. The default stacks the wells'
        models into one model call (:mod:`vfm_core.learning.stacking`), or predicts well by
        well where they cannot be stacked."""
        return Forecast(stacked_rates([m.model for m in methods], batch))

    def learn_key(self) -> Hashable | None:
        """What methods must share for :meth:`learn_group` to learn their wells' measurements
        in one call; None (the default): this method learns one well at a time."""
        return None

    @classmethod
    def learn_group(
        cls,
        methods: Sequence[LearningMethod],
        batches: Sequence[Batch],
        memories: Sequence[Memory | None],
    ) -> list[bool | None]:
        """:meth:`on_measurement` of K methods with equal :meth:`learn_key`, ``batches[k]``
        (a one-well batch) and ``memories[k]`` for ``methods[k]``. Per method: whether its
        model changed, or None where it was left to learn by itself (the caller then calls
        its :meth:`on_measurement`). An error must come before any method's state changes
        (the caller then lets each learn by itself). The default leaves every one to learn
        by itself: a new method is correct without this, only slower."""
        return [None] * len(methods)

    # -- tuning ----------------------------------------------------------------------------------
    def tuning(self, grid: str) -> list[dict[str, Any]]:
        """The settings ``vfm tune`` tries for this method with the grid ``grid`` (``small`` or
        ``paper``): each a dict of ``train`` (batch settings), ``online`` (online settings) or
        ``text`` (the method's own options, e.g. ``bayes:drift=2``). Default: the batch
        learning rate, which every retrain uses."""
        rates = [1e-1, 1e-2, 1e-3] + ([1e-4, 1e-5] if grid == "paper" else [])
        return [{"train": {"lr": lr}} for lr in rates]

    # -- what the method knows -------------------------------------------------------------------
    def parameter_sd(self) -> dict[str, torch.Tensor]:
        """Posterior standard deviation [W] of the physical parameters, SI units, by the names of
        ``model.physical_parameters()``; empty for a method that keeps no uncertainty."""
        return {}

    def stats(self) -> dict[str, torch.Tensor]:
        """Per-well counters worth reporting (e.g. refused outliers) [W]; empty by default."""
        return {}

    # -- state -----------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {
            "iterations": self.iterations.clone(),
            "chosen_on": self.chosen_on.clone(),
            "retrains": list(self.retrains[-100:]),
            "n_retrains": self.n_retrains,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "iterations" in state:
            self.iterations = torch.as_tensor(state["iterations"]).clone()
            # a checkpoint from before: the counts were chosen on no known number of
            # measurements, so the next retrain chooses them again
            self.chosen_on = torch.as_tensor(
                state.get("chosen_on", torch.zeros_like(self.iterations))
            ).clone()
        self.retrains = [int(t) for t in state.get("retrains", [])]
        self.n_retrains = int(state.get("n_retrains", len(self.retrains)))


def ready_for_group(methods: Sequence[LearningMethod], batches: Sequence[Batch]) -> list[int]:
    """For a stacked update (``learn_group``): set up each method's model on its one-well
    batch (as its own update does first), and return the places of those whose model is
    ready and that have a measurement: the ones a stacked step moves."""
    ready = []
    for k, (method, batch) in enumerate(zip(methods, batches, strict=True)):
        model = method.model
        model.setup(batch)
        if bool(model.ready[0]) and int(batch.count()[0]) > 0:
            ready.append(k)
    return ready


#: a retrain chooses a well's iteration count again by early stopping once the well holds
#: this many times the measurements the count was chosen on (the choice grew stale)
RECHOOSE_GROWTH = 2

#: every registered method by key (filled by :func:`register`)
METHODS: dict[str, type[LearningMethod]] = {}


def register(cls: type[M]) -> type[M]:
    """Class decorator: add a method to :data:`METHODS` under its key."""
    if not cls.key or cls.key in METHODS:
        raise ValueError(f"Learning method {cls.__name__} needs a unique key, not '{cls.key}'.")
    METHODS[cls.key] = cls
    return cls


def parse_method(text: str | LearningMethod) -> LearningMethod:
    """A new (unbound) method from its text, e.g. ``ol``, ``pbl:14d``, ``pbl:auto:alpha=0.05``."""
    if isinstance(text, LearningMethod):
        return type(text).from_text(text.text)
    text = str(text).strip()
    # the longest key that starts the text: pbl:auto before pbl
    for key in sorted(METHODS, key=len, reverse=True):
        if text == key or text.startswith(key + ":"):
            return METHODS[key].from_text(text)
    choices = "; ".join(f"{cls.key}: {cls.summary}" for cls in METHODS.values())
    raise ConfigError(f"Unknown learning method '{text}'. Choose one of: {choices}.")
