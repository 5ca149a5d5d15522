"""Periodic batch learning (``pbl:<period>[:window=<span>]``): retrain every period on all
measurements so far (or on the last ``window``), warm-started from the current parameters.

Retrains fall on start + k periods (the split in the study, the history's end in the
service); a well retrains when its own time passes the next one, so wells stay
independent, and wells that pass it together retrain in one batched fit. Each retrain runs
the initial fit's early-stopped iteration count per well (at most ``retrain_max_iter``).

A live well with no model yet (no history) is fitted on its first measurement at once, so
that it starts predicting; the study, which batches the predictions between two retrains,
scores such a well from the next retrain, as the paper's batch learning does.
"""

from __future__ import annotations

from typing import Any

import pandas as pd
import torch

from vfm_core.data import Batch
from vfm_core.errors import ConfigError
from vfm_core.learning.memory import Memory
from vfm_core.learning.method import NEVER, LearningMethod, parse_span, register
from vfm_core.learning.training import fit_batch
from vfm_core.models import ChokeModel

__all__ = ["PeriodicBatch"]


@register
class PeriodicBatch(LearningMethod):
    """``pbl:<period>[:window=<span>]``; see the module docstring."""

    key = "pbl"
    kind = "pbl"
    summary = "retrain every period, e.g. pbl:14d or pbl:182d:window=365d"
    example = "pbl:30d"
    per_measurement = False

    def __init__(
        self, text: str, *, period: pd.Timedelta, window: pd.Timedelta | None = None
    ) -> None:
        super().__init__(text, window=window)
        self.period = period
        #: per well, the time (epoch ns) of its next retrain; NEVER before start()
        self._next = torch.zeros(0, dtype=torch.int64)

    @classmethod
    def from_text(cls, text: str) -> PeriodicBatch:
        parts = text.split(":")
        if len(parts) < 2 or not parts[1]:
            raise ConfigError(
                f"Method '{text}' needs a period: write pbl:<period>[:window=<span>], "
                "e.g. pbl:14d or pbl:182d:window=365d."
            )
        period = parse_span(parts[1], "period", text)
        window = None
        for part in parts[2:]:
            key, _, value = part.partition("=")
            if key != "window" or not value:
                raise ConfigError(
                    f"Method '{text}': unknown option '{part}'; pbl takes window=<span>, "
                    "e.g. pbl:182d:window=365d."
                )
            window = parse_span(value, "window", text)
        return cls(text, period=period, window=window)

    def bind(self, model: ChokeModel, **kw: Any) -> PeriodicBatch:  # type: ignore[override]
        super().bind(model, **kw)
        self._next = torch.full((len(model.wells),), NEVER, dtype=torch.int64)
        return self

    def start(self, t_ns: int) -> None:
        self._next[:] = int(t_ns) + int(self.period.value)

    def next_due(self) -> int | None:
        due = int(self._next.min()) if self._next.numel() else NEVER
        return None if due == NEVER else due

    def retrain_due(self, memory: Memory, now_ns: torch.Tensor) -> torch.Tensor:
        changed = torch.zeros(len(self.model.wells), dtype=torch.bool)
        period = int(self.period.value)
        while True:
            due = (self._next != NEVER) & (now_ns != NEVER) & (self._next <= now_ns)
            if not bool(due.any()):
                return changed
            t = int(self._next[due].min())
            wells = due & (self._next == t)
            self.retrain(memory, t, None if bool(wells.all()) else wells)
            self._next[wells] += period
            changed |= wells & self.model.ready

    def _learn(self, batch: Batch, memory: Memory | None) -> torch.Tensor:
        """Starts a well that has no model yet (fitted on what it has, at once); the others
        learn at the next retrain."""
        has = batch.count() > 0
        new = has & ~self.model.ready
        if not bool(new.any()):
            unset = has & (self._next == NEVER)
            if bool(unset.any()):
                first = torch.where(
                    batch.mask, batch.time_ns, torch.full_like(batch.time_ns, NEVER)
                )
                self._next[unset] = first.min(dim=1).values[unset] + int(self.period.value)
            return torch.zeros_like(has)
        if memory is None:
            return torch.zeros_like(has)
        t = int(batch.time_ns[new].max())
        fresh = memory.batch(t + 1)
        summary = fit_batch(self.model, fresh, self.train, wells=new)
        self.chose(new, summary["iterations"], fresh.count())
        self._fitted(fresh, new)
        self._next[new] = t + int(self.period.value)
        return new

    def state_dict(self) -> dict[str, Any]:
        state = super().state_dict()
        state["next"] = self._next.clone()
        state["next_due"] = self.next_due()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        if "next" in state:
            self._next = torch.as_tensor(state["next"]).clone()
        else:  # a checkpoint from before per-well calendars: one time for every well
            nxt = state.get("next_due")
            self._next[:] = NEVER if nxt is None else int(nxt)
