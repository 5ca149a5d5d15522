"""A worker's queue: one FIFO per well, served round robin, each bounded.

The wells of one separator share one FIFO (``fifo_of``: the separator's name, which its
readings are queued under too): a reading of their total at t counts each well's sample
at t, so the worker must take them in the order they arrived, a sample of one well's next
day never before a partner's sample at the reading (with the wells in turn it did: walk57,
where a replay at full speed settled most readings with the partners not yet at t, "shut
in"). Such a FIFO holds ``well_capacity`` messages per member well (``fifo_capacity``).

Why not one FIFO per worker: a well that floods would put thousands of messages in front
of every other well's next sample (measured before this queue: 8 s of delay for a well
sending once a second while another sent 5,000 samples a second). Here each well has its
own FIFO (its messages keep their order) of at most ``well_capacity`` items, and the
worker takes one item from each well that has any, in turn. A sample of a quiet well
therefore waits behind at most one item per other busy well of its worker, however much
those send.

:meth:`FairQueue.put` waits while the well's FIFO (or the whole queue, ``capacity``) is
full, at most ``timeout`` seconds, and then says which was full, so that the receiver can
count ``well flooding`` or ``queue overflow``; ``force`` puts an item whatever the bounds
(a model swap, which must never be dropped). A sensor block counts against ``capacity``
by its memory in messages (``weight``), so the queue bounds what it holds. :meth:`FairQueue.close` makes :meth:`get`
answer :data:`CLOSED` once every queued item has been taken. :attr:`FairQueue.on_put`, when
set, is called after every put and at close, outside the lock (a worker that waits for
messages elsewhere, in Zenoh's ``recv``, is woken by it: see :class:`service.transport.Source`).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Literal

__all__ = ["FairQueue", "CLOSED"]

#: what :meth:`FairQueue.get` answers once the queue is closed and empty
CLOSED = object()


class FairQueue:
    """Per-well FIFOs served round robin; see the module docstring. Thread-safe."""

    def __init__(
        self,
        capacity: int,
        well_capacity: int,
        *,
        fifo_of: Callable[[str], str] | None = None,
        fifo_capacity: Callable[[str], int] | None = None,
    ) -> None:
        self.capacity = capacity
        self.well_capacity = well_capacity
        #: the FIFO a well's items go to (its separator's, else its own)
        self._fifo_of = fifo_of or (lambda well: well)
        #: how many items a FIFO holds (default ``well_capacity``)
        self._fifo_capacity = fifo_capacity or (lambda fifo: well_capacity)
        self._lock = threading.Lock()
        self._has_items = threading.Condition(self._lock)
        self._has_room = threading.Condition(self._lock)
        self._queues: dict[str, deque[Any]] = {}
        #: wells with queued items, in the order they are served
        self._ring: deque[str] = deque()
        self._size = 0
        self._closed = False
        self._waiting = 0
        #: callers waiting in :meth:`get` (a put notifies only when there are any)
        self._getting = 0
        #: called after every put and at close, outside the lock (see the module docstring)
        self.on_put: Callable[[], None] | None = None

    @property
    def closed(self) -> bool:
        return self._closed

    def qsize(self) -> int:
        """What is queued: messages, a sensor block counted by its weight."""
        return self._size

    def depth(self, well: str) -> int:
        """Items queued in ``well``'s FIFO (its separator's, shared with its partners)."""
        q = self._queues.get(self._fifo_of(well))
        return 0 if q is None else len(q)

    def busy_wells(self) -> int:
        """Wells with queued items."""
        return len(self._ring)

    def put(
        self,
        well: str,
        item: Any,
        timeout: float | None = 0.0,
        *,
        force: bool = False,
        weight: int = 1,
    ) -> Literal["ok", "well", "total"]:
        """Queue ``item`` for ``well``: ``ok``, or which bound stayed full for ``timeout`` s
        (``well``: the well's own FIFO; ``total``: the whole queue). None waits for ever.

        ``weight``: what the item counts against ``capacity`` (a sensor block: its memory
        in messages, so that the queue bounds what it holds, not only how many messages);
        an item heavier than the whole capacity waits for an empty queue."""
        weight = max(1, min(weight, self.capacity))
        deadline = None if timeout is None else time.monotonic() + timeout
        fifo = self._fifo_of(well)
        room = self._fifo_capacity(fifo)
        with self._lock:
            while not force:
                q = self._queues.get(fifo)
                if q is not None and len(q) >= room:
                    full: Literal["well", "total"] = "well"
                elif self._size + weight > self.capacity:
                    full = "total"
                else:
                    break
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return full
                self._waiting += 1
                try:
                    self._has_room.wait(remaining)
                finally:
                    self._waiting -= 1
            q = self._queues.get(fifo)
            if q is None:
                q = self._queues[fifo] = deque()
                self._ring.append(fifo)
            q.append((item, weight))
            self._size += weight
            if self._getting:  # a worker waits in get (not when it takes messages itself)
                self._has_items.notify()
        if self.on_put is not None:
            self.on_put()
        return "ok"

    def get(self, timeout: float | None = None) -> Any:
        """The next item (round robin over wells); None after ``timeout`` s without one;
        :data:`CLOSED` once closed and empty."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            while not self._ring:
                if self._closed:
                    return CLOSED
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._getting += 1
                try:
                    self._has_items.wait(remaining)
                finally:
                    self._getting -= 1
            return self._pop()

    def get_nowait(self) -> Any:
        """The next item, or None when nothing is queued (:data:`CLOSED` once closed)."""
        with self._lock:
            if not self._ring:
                return CLOSED if self._closed else None
            return self._pop()

    def get_many(self, limit: int) -> list[Any]:
        """Up to ``limit`` items in the order :meth:`get_nowait` would give them, under one
        lock (a worker takes many single samples in a row); [] when nothing is queued,
        ``[CLOSED]`` once closed and empty."""
        with self._lock:
            if not self._ring:
                return [CLOSED] if self._closed else []
            ring, queues = self._ring, self._queues
            out: list[Any] = []
            freed = 0
            while ring and len(out) < limit:
                well = ring.popleft()
                q = queues[well]
                item, weight = q.popleft()
                if q:
                    ring.append(well)
                else:
                    del queues[well]
                freed += weight
                out.append(item)
            self._size -= freed
            if self._waiting:
                self._has_room.notify_all()
            return out

    def _pop(self) -> Any:
        well = self._ring.popleft()
        q = self._queues[well]
        item, weight = q.popleft()
        if q:
            self._ring.append(well)
        else:
            del self._queues[well]
        self._size -= weight
        if self._waiting:
            self._has_room.notify_all()
        return item

    def close(self) -> None:
        """No more items are expected: :meth:`get` answers :data:`CLOSED` once empty."""
        with self._lock:
            self._closed = True
            self._has_items.notify_all()
        if self.on_put is not None:
            self.on_put()

    def drain(self) -> list[Any]:
        """Take every queued item (at a stop, to answer the callers still waiting)."""
        with self._lock:
            items = [item for well in self._ring for item, _ in self._queues[well]]
            self._queues.clear()
            self._ring.clear()
            self._size = 0
            self._has_room.notify_all()
            return items
