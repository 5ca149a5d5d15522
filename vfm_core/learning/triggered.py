"""Drift-triggered batch learning (``pbl:auto[:alpha=..:confirm=..:reference=..:window=..]``).

Each well carries a streaming Hotelling T^2 test on its inputs
(:class:`vfm_core.hotelling.StreamingHotelling`), its reference window the latest
``reference`` inputs of the initial fit. When the test confirms that the inputs left
the reference (``confirm`` consecutive detections at level ``alpha``), the well is
retrained before its next measurement on every measurement up to the one that confirmed
it, and the test restarts from the latest ``reference`` inputs.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import Batch
from vfm_core.hotelling import StreamingHotelling
from vfm_core.learning.memory import Memory
from vfm_core.learning.method import (
    NEVER,
    LearningMethod,
    parse_options,
    parse_span,
    register,
)
from vfm_core.models import ChokeModel

__all__ = ["DriftTriggered"]


@register
class DriftTriggered(LearningMethod):
    """``pbl:auto``; see the module docstring."""

    key = "pbl:auto"
    kind = "auto"
    summary = (
        "retrain a well when a Hotelling T^2 test confirms its inputs drifted, "
        "e.g. pbl:auto:alpha=0.01:confirm=5"
    )
    example = "pbl:auto:alpha=0.05:confirm=2:reference=30"
    # the service runs its own drift test (drift.on_drift = "retrain")
    streaming = False

    def __init__(
        self,
        text: str = "pbl:auto",
        *,
        alpha: float = 0.01,
        confirm: int = 5,
        reference: int = 200,
        window: pd.Timedelta | None = None,
    ) -> None:
        super().__init__(text, window=window)
        self.alpha = alpha
        self.confirm = confirm
        self.reference = reference
        # checked at once: a bad alpha fails before any training
        StreamingHotelling(reference, alpha, confirm)
        self._detectors: list[StreamingHotelling] = []
        self._recent: list[deque[np.ndarray]] = []
        self._due = torch.zeros(0, dtype=torch.int64)

    @classmethod
    def from_text(cls, text: str) -> DriftTriggered:
        options = parse_options(
            text,
            text[len(cls.key) :],
            {"alpha": float, "confirm": int, "reference": int, "window": str},
            "pbl:auto:alpha=0.01:confirm=5",
        )
        window = options.pop("window", None)
        return cls(text, window=parse_span(window, "window", text) if window else None, **options)

    def bind(self, model: ChokeModel, **kw: Any) -> DriftTriggered:  # type: ignore[override]
        super().bind(model, **kw)
        n = len(model.wells)
        self._detectors = [
            StreamingHotelling(self.reference, self.alpha, self.confirm) for _ in range(n)
        ]
        self._recent = [deque(maxlen=self.reference) for _ in range(n)]
        self._due = torch.full((n,), NEVER, dtype=torch.int64)
        return self

    def _reset_references(self, batch: Batch) -> None:
        """Each well's test starts from its latest ``reference`` fitted inputs."""
        for j, det in enumerate(self._detectors):
            rows = batch.x[j][batch.mask[j]].numpy()[-self.reference :]
            self._recent[j].clear()
            self._recent[j].extend(rows)
            det.reset(rows if len(rows) >= self.reference else None)

    def fit(self, batch: Batch, *, converge: bool = False) -> None:
        super().fit(batch, converge=converge)
        self._reset_references(batch)

    def adopt(self, batch: Batch, iterations: torch.Tensor) -> None:
        super().adopt(batch, iterations)
        self._reset_references(batch)

    def next_due(self) -> int | None:
        due = int(self._due.min()) if self._due.numel() else NEVER
        return None if due == NEVER else due

    def retrain_due(self, memory: Memory, now_ns: torch.Tensor) -> torch.Tensor:
        ready = (self._due != NEVER) & (now_ns != NEVER) & (self._due <= now_ns)
        for t in sorted(set(self._due[ready].tolist())):
            wells = ready & (self._due == t)
            # on every measurement up to the confirming one, done before the next measurement
            self.retrain(memory, int(t), wells, at_ns=int(now_ns[wells].min()))
            self._due[wells] = NEVER
        return ready

    def _learn(self, batch: Batch, memory: Memory | None) -> torch.Tensor:
        for j, det in enumerate(self._detectors):
            for k in torch.nonzero(batch.mask[j]).flatten().tolist():
                row = batch.x[j, k].numpy()
                det.update(row)
                self._recent[j].append(row)
                if det.drift_detected:
                    # retrain before the next measurement, on everything up to this one
                    self._due[j] = int(batch.time_ns[j, k]) + 1
                    recent = np.asarray(self._recent[j])
                    det.reset(recent if len(recent) >= self.reference else None)
        return torch.zeros(batch.n_wells, dtype=torch.bool)

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["detectors"] = [d.state_dict() for d in self._detectors]
        state["recent"] = [[list(map(float, r)) for r in q] for q in self._recent]
        state["due"] = self._due.clone()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        for det, s in zip(self._detectors, state.get("detectors", []), strict=False):
            det.load_state_dict(s)
        for q, rows in zip(self._recent, state.get("recent", []), strict=False):
            q.clear()
            q.extend(np.asarray(r, dtype=float) for r in rows)
        if "due" in state:
            self._due = torch.as_tensor(state["due"]).clone()
