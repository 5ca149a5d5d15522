"""The calibration pools of ``bayes:cal_pool=on``: the service's one-well filters share them.

With ``cal_pool=on`` each well's well-test variance factor takes its prior from the other
wells' well-test errors (:mod:`vfm_core.learning.bayes`, "Pooled over the wells"). The
study runs one filter over all the wells; the service runs one filter a well. So the
engine holds one :class:`~vfm_core.learning.bayes.CalibrationPool` per model and method
(the wells whose filters could learn in one stacked update: the same model specification
and the same method text), and each well's live learner joins its pool when it becomes
the well's learner (:meth:`Pools.join`: at start-up, a new well, a model change, a
rollback, the end of a trial). A learner joining publishes its well's statistics (a
restored one brings its own back), so after a restart the pools are rebuilt from the
checkpoints and the measurements re-learned from the store. A well that leaves (retired,
or its learner replaced by one of another model or method, or one without ``cal_pool``)
is forgotten by its pool. Scratch copies (a model change's fit, a trial's shadow) never
join: they are one-well filters with the stated prior.
"""

from __future__ import annotations

import threading
from collections.abc import Hashable
from typing import Any

from vfm_core.learning.bayes import BayesianFilter, CalibrationPool

__all__ = ["Pools", "coupled"]


def coupled(learner: Any) -> bool:
    """Whether ``learner``'s method couples it with the other wells' learners through a
    pool (``bayes`` with ``cal_pool=on`` on a well's own model)."""
    return _key(learner) is not None


def _key(learner: Any) -> Hashable | None:
    """The pool of ``learner``'s well: one per model specification and method text (None:
    no pool: the method does not pool, or the model is field-wide, one filter over all
    its wells already)."""
    method = getattr(learner, "method", None)
    if not isinstance(method, BayesianFilter) or getattr(learner, "shares_model", False):
        return None
    if not method.cal_pool or method.cal_prior <= 0 or method.model.gradient_free:
        return None
    return (method.model.stack_key(), method.text)


class Pools:
    """The engine's calibration pools (see the module docstring). Thread-safe: wells of
    several workers join and leave."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pools: dict[Hashable, CalibrationPool] = {}
        #: the pool each well's learner is in, and that learner
        self._member: dict[str, CalibrationPool] = {}
        self._learner: dict[str, Any] = {}

    def join(self, well: str, learner: Any) -> None:
        """Make ``learner`` the one of ``well`` in the pools: it shares its model's and
        method's pool (publishing its statistics there), or none; ``well`` leaves the pool
        of its previous learner if that was another."""
        key = _key(learner)
        with self._lock:
            pool = None if key is None else self._pools.setdefault(key, CalibrationPool())
            before = self._member.pop(well, None)
            replaced = self._learner.pop(well, None)
            if pool is not None:
                self._member[well] = pool
                self._learner[well] = learner
        if replaced is not None and replaced is not learner:
            _detach(replaced)  # (it may run on as a trial's shadow: alone, not in the pool)
        if before is not None and before is not pool:
            before.forget(well)
        if pool is not None:
            learner.method.share_errors(pool)

    def leave(self, well: str) -> None:
        """``well`` is no longer served (retired): its pool forgets it."""
        with self._lock:
            before = self._member.pop(well, None)
            replaced = self._learner.pop(well, None)
        if replaced is not None:
            _detach(replaced)
        if before is not None:
            before.forget(well)

    def members(self) -> dict[str, int]:
        """Each pooled well and the number of wells in its pool (for tests and logs)."""
        with self._lock:
            sizes: dict[int, int] = {}
            for pool in self._member.values():
                sizes[id(pool)] = sizes.get(id(pool), 0) + 1
            return {well: sizes[id(pool)] for well, pool in self._member.items()}


def _detach(learner: Any) -> None:
    """Take a learner that is no longer its well's out of its pool: it neither publishes
    there nor reads the other wells' errors (its factor's prior is the stated one again)."""
    method = learner.method
    method.share_errors(None)
    method.pool_with(None)
