"""The durable record of each well's physical parameters over time (``parameter_history``).

After a learning step has refreshed the well's snapshot (its parameters with their
standard deviation where the method keeps one), :meth:`ParameterHistory.maybe` adds a
row to the same batch as the learning, so the record is never ahead of the data. It is
thinned: a row when the model's version moved by ``store.parameters_every`` since the
well's last row, or when the model's name changed (a model change, whose parameters
differ: an effect adds e.g. ``erosion.rate``), and each row prunes the well's rows beyond
``store.parameters_kept`` (the oldest). A row's time is the data time of the measurement
(or sample, for a retrain) it follows, never the wall clock.
"""

from __future__ import annotations

import json
import math

from service.config import Settings
from service.engine.state import WellState
from service.store import InsertParameters, Op, PruneParameters

__all__ = ["ParameterHistory"]


class ParameterHistory:
    """Decides when a well's parameters are recorded, and writes the row."""

    def __init__(self, settings: Settings) -> None:
        self.every = settings.store.parameters_every
        self.keep = settings.store.parameters_kept

    def ops(self, st: WellState, time_ns: int) -> list[Op]:
        """The writes of a row of the well's current parameters at ``time_ns`` (none when the
        model has no physical parameters, or is not ready)."""
        params = st.snapshot.get("parameters") or {}
        if not params:
            return []
        learner = st.learner
        st.params_version, st.params_model = learner.version, learner.name
        return [
            InsertParameters(
                well=st.well,
                time_ns=time_ns,
                version=learner.version,
                model=learner.name,
                parameters=json.dumps(
                    {name: {k: _clean(v) for k, v in p.items()} for name, p in params.items()}
                ),
            ),
            PruneParameters(well=st.well, keep=self.keep),
        ]

    def maybe(self, st: WellState, time_ns: int, ops: list[Op]) -> None:
        """Record the parameters if due (see the module docstring)."""
        learner = st.learner
        if (
            st.params_version is None
            or st.params_model != learner.name
            or learner.version - st.params_version >= self.every
        ):
            ops.extend(self.ops(st, time_ns))


def _clean(value: object) -> object:
    """JSON has no NaN or infinity: a value without a finite number is stored as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
