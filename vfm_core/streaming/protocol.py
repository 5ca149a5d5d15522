"""What serves one well, whatever model it runs: the :class:`Learner` protocol.

Two classes serve a well: :class:`vfm_core.streaming.WellLearner` (a per-well model and
its method) and :class:`vfm_core.field_learner.FieldWell` (the well's facade on a
field-wide model such as ``mtl``, whose network all wells share). Both keep this
protocol, and the service may hold either through it: predict a sample, learn from a
measurement, retrain, report the physical parameters, checkpoint, and say what it is and
how far it has come. What only one of them does (a per-well model change, a block of
samples in one model call) is asked of :class:`WellLearner` alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from typing import Any, Protocol, runtime_checkable

import pandas as pd
import torch

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
