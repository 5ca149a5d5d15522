"""What passes between the engine's threads: queued items, and what one worker batch collects.

The receiver thread (and the HTTP threads) put :class:`SensorItem`,
:class:`MeasurementItem`, :class:`ModelStep` and :class:`RetireStep` on a worker's queue
(:class:`~service.engine.fairqueue.FairQueue`, in the FIFO of their well); the worker handles
them in arrival order into a :class:`Batch`: the store writes, the predictions to
publish and the answers for waiting callers, all released after one commit.
"""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from service.engine.state import Pending, Sample, WellTestResult
from service.errors import ServiceError
from service.inputs import Counters
from service.store import Op
from vfm_core.learning.streaming import WellLearner
from vfm_core.messages import Measurement
from vfm_core.sensor_faults import Fallback

__all__ = [
    "SensorItem",
    "SensorBlockItem",
    "MeasurementItem",
    "ModelStep",
    "RetireStep",
    "Item",
    "Batch",
    "DeferredLearn",
    "refuse",
]


@dataclass(slots=True)
class SensorItem:
    """A well's single sensor sample, checked: its time (epoch ns) and six inputs (file
    units, in :data:`vfm_core.schema.INPUT_COLUMNS` order)."""

    well: str
    time_ns: int
    inputs: tuple[float, ...]
    received_ns: int
    #: the stand-ins its prediction uses (empty: none), once fed to the instrument-fault
    #: detectors (:meth:`WellState.watch_sample
    #: <service.engine.state.WellState.watch_sample>`, at admission, or with its sensor
    #: block); None: not fed yet
    stand_ins: tuple[Fallback, ...] | None = None


@dataclass(slots=True)
class SensorBlockItem:
    """A well's samples from one sensor block, checked and in rising time order: times
    [N] (epoch ns) and inputs [N, 6] (file units)."""

    well: str
    times_ns: Any  # np.ndarray [N] int64
    inputs: Any  # np.ndarray [N, 6]
    received_ns: int


@dataclass(slots=True)
class MeasurementItem:
    well: str
    measurement: Measurement
    source: str  # mpfm | well_test
    received_ns: int
    via: str = "zenoh"  # zenoh | http
    future: Future[WellTestResult] | None = None


@dataclass
class ModelStep:
    """A step of a model change, run by the well's worker: take a copy, or swap in the new model."""

    well: str
    kind: str  # snapshot | swap | cancel
    future: Future[Any]
    learner: WellLearner | None = None
    scores: dict[str, Any] = field(default_factory=dict)


@dataclass
class RetireStep:
    """Retire a well (``DELETE /wells/{well}``), run by its worker after what was queued before."""

    well: str
    purge: bool
    when_ns: int
    future: Future[Any]


Item = SensorItem | SensorBlockItem | MeasurementItem | ModelStep | RetireStep


@dataclass(slots=True)
class DeferredLearn:
    """A paired measurement whose learning step waits for the batch's one
    :func:`~vfm_core.learning.streaming.learn_many` call (see :meth:`Learning.learn_paired
    <service.engine.learning.Learning.learn_paired>`): the well, the measurement, its sample,
    and what a well-test caller is answered with (the version and prediction before)."""

    st: Any  # WellState
    pending: Pending
    sample: Sample
    version_before: int
    before: dict[str, float | None]


class Batch:
    """What one worker batch writes, publishes and answers (after one commit)."""

    __slots__ = (
        "ops",
        "outbox",
        "answers",
        "samples",
        "sample_wells",
        "sample_due",
        "sample_last",
        "learns",
        "learn_wells",
    )

    def __init__(self) -> None:
        self.ops: list[Op] = []
        self.outbox: list[tuple[str, bytes]] = []  # (well, prediction JSON)
        self.answers: list[tuple[Future[Any], Any]] = []  # (future, result or exception)
        #: sensor samples admitted and waiting for the batch's one prediction call:
        #: (well state, item, time ns, inputs), in arrival order
        self.samples: list[tuple[Any, SensorItem, int, tuple[float, ...]]] = []
        #: the wells among them -> whether another sample of the well may join the call
        self.sample_wells: dict[str, bool] = {}
        #: those of them whose model may change only by a scheduled retrain (``pbl``, or
        #: ``bayes``'s refresh of a hybrid learning from well tests): another sample joins
        #: the call when it comes before the retrain is due
        self.sample_due: set[str] = set()
        #: each of those wells' latest admitted sample: (time ns, inputs), for the order check
        self.sample_last: dict[str, tuple[int, tuple[float, ...]]] = {}
        #: paired measurements waiting for the batch's one learning call, in pairing order
        self.learns: list[DeferredLearn] = []
        #: the wells among them: any other item of such a well waits for that call
        self.learn_wells: set[str] = set()

    def answer(self, future: Future[Any] | None, result: Any) -> None:
        """Answer ``future`` (if any) with a result or an exception, once the batch is committed."""
        if future is not None:
            self.answers.append((future, result))

    def clear(self) -> None:
        """Forget what was committed (the deferred learns were run before any commit)."""
        self.ops, self.outbox, self.answers = [], [], []


def refuse(
    counters: Counters,
    error: ServiceError,
    where: str,
    batch: Batch,
    future: Future[Any] | None = None,
) -> None:
    """Count a refused input under its reason and answer its caller (if one waits)."""
    if error.reason is not None:
        counters.reject(error.reason, error.message, where=where, well=where)
    batch.answer(future, error)
