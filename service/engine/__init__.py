"""The service's core, free of Zenoh and HTTP: per-well state, workers, pairing, learning.

Find each job by its module: ``recovery`` (restore from checkpoints, re-learn after them,
fit on the history), ``intake`` (receiving, routing to workers, back-pressure),
``worker`` (the worker loop, group commit, publishing, answering callers), ``pairing``
(a measurement with the nearest sensor sample; pending measurements), ``learning``
(predict, learn, rolling error, drift detector), ``checkpoints``, ``model_change``
(``PUT /wells/{well}/model``: snapshot, refit off the worker, catch-up, swap), ``state``
(what is kept per well), ``items`` (what passes between threads), ``fairqueue`` (a
worker's queue: one FIFO per well, served round robin) and ``registry`` (which wells
exist; admitting new ones, retiring). :class:`Engine`
(``core``) is the facade the service and the HTTP layer use.
"""

from service.engine.core import Engine
from service.engine.state import WellState, WellTestResult

__all__ = ["Engine", "WellState", "WellTestResult"]
