"""What serves one well, whatever model it runs: the :class:`Learner` protocol.

Two classes serve a well: :class:`vfm_core.learning.streaming.WellLearner` (a per-well model and
its method) and :class:`vfm_core.learning.field.FieldWell` (the well's facade on a
field-wide model such as ``mtl``, whose network all wells share). Both keep this
protocol, and the service may hold either through it: predict a sample, learn from a
measurement, retrain, report the physical parameters, checkpoint, and say what it is and
how far it has come.

What differs between them is asked, never read off the class: whether the model is
shared with other wells (:attr:`Learner.shares_model`: a step for one well then moves the
others', so its steps keep arrival order and its model cannot be changed, rolled back or
run as a trial's shadow for one well alone), what a checkpoint holds besides the well
(:attr:`Learner.checkpoint_group`: the field whose one snapshot serves all its wells),
whether many learners' predictions and updates can share one model call
(:attr:`Learner.predicts_in_groups`, :attr:`Learner.learns_in_groups`), the bound on what
it remembers (:meth:`Learner.remember_at_most`), what becomes of a measurement it has not
learned yet (:meth:`Learner.deferred_note`); and what one of them refuses with a sentence
(a field-wide well: a block of samples in one call, :meth:`Learner.predict_block`; a new
version number of its own, :meth:`Learner.renumber`; the initial fit of one well on its
history, :meth:`Learner.fit_history`, :meth:`Learner.adopt_fit`, since the field is
fitted as a whole). So the service holds, checkpoints and serves a third kind of learner
that keeps this protocol without an edit; only what reads a per-well checkpoint back (a
restart, a model change's copy, a trial's shadow, a rollback) uses
:meth:`vfm_core.learning.streaming.WellLearner.restore` by name.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from typing import Any, Protocol, runtime_checkable

import numpy as np
import pandas as pd
import torch

from vfm_core.features import FeatureTracker
from vfm_core.learning import LearningMethod, OnlineSettings, TrainSettings, WellMemory
from vfm_core.models import ChokeModel

__all__ = ["Learner"]


@runtime_checkable
class Learner(Protocol):
    """One well's learner: a sample in, rates out (Sm3/h); a measurement in, learned."""

    #: the well's name
    well: str
    #: the batch settings of its fits (the service sets the wall-clock budget)
    train: TrainSettings

    @property
    def model_name(self) -> str:
        """The registry name of the model (``mm``, ``mtl``, ...)."""
        ...

    @property
    def name(self) -> str:
        """The model's full name, with its effects (``mm+erosion``)."""
        ...

    @property
    def model(self) -> ChokeModel: ...

    @property
    def method(self) -> LearningMethod: ...

    @property
    def effects(self) -> list[str]: ...

    @property
    def online(self) -> OnlineSettings: ...

    @property
    def model_kwargs(self) -> dict[str, Any]: ...

    @property
    def seed(self) -> int: ...

    @property
    def version(self) -> int:
        """How many times the model changed (a fit, an update, a retrain)."""
        ...

    @property
    def n_updates(self) -> int: ...

    @property
    def last_update(self) -> datetime | None: ...

    @property
    def memory(self) -> WellMemory:
        """The measurements kept for retrains and model changes."""
        ...

    @property
    def remembered(self) -> int: ...

    @property
    def ready(self) -> bool:
        """True once the model can predict (before that, every rate is None)."""
        ...

    def predict(
        self, inputs: Sequence[float] | torch.Tensor, when: datetime | None = None
    ) -> dict[str, float | None]:
        """Rates (Sm3/h) for one sample's six inputs (file units) at ``when``."""
        ...

    def predict_block(self, inputs: np.ndarray, times_ns: np.ndarray) -> dict[str, np.ndarray]:
        """:meth:`predict` for a block of one well's samples in time order ([N, 6] file units,
        [N] epoch ns) in one model call: arrays [N] of the same keys. ValueError where the
        learner cannot (its model may change while predicting, not ready, shared): the
        caller then predicts the samples one by one."""
        ...

    def learn(
        self,
        inputs: Sequence[float] | torch.Tensor,
        q_total: float,
        when: datetime,
        source: str = "mpfm",
    ) -> bool:
        """Learn from one measured total rate (Sm3/h); True when the model changed."""
        ...

    def retrain(self, now: datetime | pd.Timestamp) -> None: ...

    def physical_parameters(self) -> dict[str, dict[str, Any]]: ...

    def refit_as(self, *args: Any, **kwargs: Any) -> Any:
        """Another model on the same history (refused where the model is shared)."""
        ...

    def checkpoint(self) -> bytes: ...

    # -- what it can do (capabilities: asked, never read off the class) ------------------------
    @property
    def shares_model(self) -> bool:
        """True when the model is shared with other wells (a field-wide model): a step for
        this well changes the others' predictions, so its steps run in arrival order (never
        deferred to a batch's end), and its model cannot be changed, rolled back or run on
        as a trial's shadow for this well alone."""
        ...

    @property
    def checkpoint_group(self) -> object | None:
        """None when :meth:`checkpoint` holds this well alone (and restores it alone);
        otherwise the object (hashable, weak-referenceable) shared by every learner whose
        checkpoint is the same snapshot (the field), so that one snapshot serves them all."""
        ...

    @property
    def predicts_in_groups(self) -> bool:
        """True when :func:`vfm_core.learning.streaming.predict_many` may split :meth:`predict` around
        one model call shared with other learners (``prepare_sample``, ``sample_batch``,
        ``answer``); False: it answers through its own :meth:`predict`."""
        ...

    @property
    def learns_in_groups(self) -> bool:
        """True when :func:`vfm_core.learning.streaming.learn_many` may split :meth:`learn` around one
        update shared with other learners (``take_measurement``, ``learn_taken``); False:
        it learns through its own :meth:`learn`."""
        ...

    def renumber(self, at_least: int) -> None:
        """Give the model the version ``at_least`` if its own is lower (a model swapped in
        for another continues its versions); refused where the version is shared."""
        ...

    def remember_at_most(self, rows: int | None) -> None:
        """Keep at most ``rows`` measurements (the latest; None: all) for retrains and model
        changes, where the learner can bound them alone."""
        ...

    def deferred_note(self) -> str:
        """What becomes of a measurement taken without changing the model now, as a
        sentence (for the caller who sent it)."""
        ...

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
        """The well's initial fit on its history alone: inputs [N, 6], rates [N] Sm3/h,
        times [N] epoch ns (refused where the model is shared: the field is fitted whole)."""
        ...

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
        """Take on an initial fit of this well done elsewhere (its model already holds it),
        as :meth:`fit_history` would have left it (refused where the model is shared)."""
        ...
