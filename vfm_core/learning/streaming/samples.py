"""One sample or measurement of one well as the learner holds it: plain numbers and batches.

Helpers of :class:`vfm_core.learning.streaming.WellLearner` and of the many-wells calls
(:func:`vfm_core.learning.streaming.predict_many`, :func:`vfm_core.learning.streaming.learn_many`): a
sample's time in epoch ns, its six inputs as floats, a one-sample batch, and a well's
history as the tensors its memory stores.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime

import torch

from vfm_core.data import DTYPE, Batch
from vfm_core.features import FeatureTracker
from vfm_core.timeutil import to_ns, utc_timestamp

__all__ = ["Row", "epoch_ns", "six_inputs", "one_sample", "history_rows"]

#: one prepared sample: its six inputs, its time (epoch ns) and the model's feature columns
Row = tuple[list[float], int, list[float]]


def epoch_ns(when: datetime | int) -> int:
    """Epoch nanoseconds of a sample's time: :func:`utc_timestamp`'s ``.value``, without a
    pandas Timestamp for a plain datetime (microseconds: exact integer arithmetic); an int
    is epoch ns already."""
    if type(when) is int:
        return when
    if type(when) is datetime:
        return to_ns(when)
    return int(utc_timestamp(when).value)


def six_inputs(inputs: Sequence[float] | torch.Tensor) -> list[float]:
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


def one_sample(
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


def history_rows(
    x: torch.Tensor,
    y: torch.Tensor,
    t: torch.Tensor,
    well_test: torch.Tensor | None,
    features: torch.Tensor | None,
    tracker: FeatureTracker | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, FeatureTracker]:
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
