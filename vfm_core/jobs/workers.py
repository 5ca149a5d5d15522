"""Worker processes that share a list of tasks with the process that asks for them.

``vfm evaluate --jobs N`` runs the study's model groups N at a time: the calling process
takes groups itself while N - 1 spawned workers start (importing torch and the kernels
takes a few seconds); a worker gets a group only once it is ready, so a small study never
waits for a worker to start: at worst the caller ran everything alone. Workers are spawned,
never forked (torch, tqdm and numba hold threads), and live until :meth:`StudyWorkers.close`,
so the two cases of one ``vfm evaluate`` share them.

A task's function must be a module-level callable ``fn(task, report)``; ``report(n)`` adds
``n`` to the caller's progress. Tasks and results travel pickled between this process and
its own workers only (nothing from outside is unpickled). An exception in a task is raised
again in the caller, with the worker's traceback as a note; a worker that dies (killed, out
of memory) ends the run with an error naming its exit code. Ctrl-C reaches the caller only
(workers ignore SIGINT) and the caller stops the workers.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import signal
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

__all__ = ["StudyWorkers", "usable_cpus"]

logger = logging.getLogger("vfm.workers")

#: a worker sends its progress at most this often, s
_PROGRESS_EVERY_S = 0.25
#: how often the caller checks that its workers are alive while it waits, s
_POLL_S = 0.5


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the system tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _worker_main(  # noqa: PLR0913 - what a spawned worker is given
    tasks: Any,
    results: Any,
    threads: int,
    preload: tuple[str, ...],
    gate: Any = None,
    flags: Any = None,
    slot: int = 0,
) -> None:
    """A worker: import what the tasks need, say it is ready, then run tasks until told to
    stop. ``gate``, ``flags``: see :meth:`StudyWorkers.close` (flags[0]: closing;
    flags[1 + slot]: this worker may take from the task queue)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller handles Ctrl-C and stops us
    import importlib

    from vfm_core.runtime import configure

    configure(threads)
    for name in preload:
        importlib.import_module(name)
    from vfm_core.learning import kernels

    kernels.warm()
    if gate is not None:
        with gate:  # once marked, close() sends this worker its stop, never terminates it
            if flags[0]:
                return
            flags[1 + slot] = 1
    results.put(("ready", os.getpid()))
    while True:
        item = tasks.get()
        if item is None:
            return
        index, fn, task = item
        results.put(("took", index, os.getpid()))
        pending = [0, time.monotonic()]

        def report(n: int, pending: list[Any] = pending) -> None:
            pending[0] += n
            now = time.monotonic()
            if now - pending[1] >= _PROGRESS_EVERY_S:
                results.put(("progress", pending[0]))
                pending[0], pending[1] = 0, now

        try:
            out = fn(task, report)
        except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
            results.put(("error", index, _portable(exc), traceback.format_exc()))
        else:
            if pending[0]:
                results.put(("progress", pending[0]))
            results.put(("done", index, out))


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its text."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc


class StudyWorkers:
    """``workers`` spawned processes that run tasks beside the caller (see the module).

    ``threads``: torch's threads in each worker (default: this process's); ``preload``:
    modules a worker imports before it says it is ready (the tasks' own, so that a ready
    worker starts a task at once)."""

    def __init__(
        self,
        workers: int,
        *,
        threads: int | None = None,
        preload: Sequence[str] = ("vfm_core.jobs.study",),
    ) -> None:
        if workers < 0:
            raise ValueError("The number of workers cannot be negative.")
        if threads is None:
            import torch

            threads = torch.get_num_threads()
        self.workers = int(workers)
        self._threads = int(threads)
        self._preload = tuple(preload)
        self._procs: list[Any] = []
        self._tasks: Any = None
        self._results: Any = None
        self._reader: threading.Thread | None = None
        self._cond = threading.Condition()
        self._idle = 0
        #: close() and the workers' ready marks (see close): a lock and [closing, ready...]
        self._gate: Any = None
        self._flags: Any = None
        self._closed = False
        self._run: dict[str, Any] | None = None

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> StudyWorkers:
        if self._procs or self.workers == 0:
            return self
        ctx = mp.get_context("spawn")
        self._tasks, self._results = ctx.Queue(), ctx.Queue()
        self._gate, self._flags = ctx.Lock(), ctx.Array("b", self.workers + 1, lock=False)
        for i in range(self.workers):
            proc = ctx.Process(
                target=_worker_main,
                args=(
                    self._tasks,
                    self._results,
                    self._threads,
                    self._preload,
                    self._gate,
                    self._flags,
                    i,
                ),
                daemon=True,
                name="vfm-study-worker",
            )
            proc.start()
            self._procs.append(proc)
        self._reader = threading.Thread(target=self._read, name="vfm-study-results", daemon=True)
        self._reader.start()
        return self

    def close(self) -> None:
        """Stop the workers: idle ones are told to end (a worker killed while it waits on
        the task queue may hold the queue's lock, and then the others never get their
        stop); one still importing is terminated (it has not touched the queue: under the
        shared ``gate`` it either marked itself ready before ``close`` looked, or sees the
        closing flag and ends); a task still running is abandoned, its worker terminated."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            busy = self._run is not None and bool(self._run["outstanding"])
            self._cond.notify_all()
        if not busy and self._tasks is not None:
            # no worker marks itself ready from here on; the workers not marked never take
            # from the task queue, so they hold none of its locks and may be terminated. A
            # gate that stays taken means a worker was killed from outside inside it: then
            # none is known to be safe, and all are terminated.
            got = self._gate.acquire(timeout=5.0)
            self._flags[0] = 1
            marked = [got and bool(self._flags[1 + i]) for i in range(len(self._procs))]
            if got:
                self._gate.release()
            for _ in self._procs:
                self._tasks.put(None)
            for proc, ready in zip(self._procs, marked, strict=True):
                if not ready:
                    proc.terminate()
            deadline = time.monotonic() + 10.0
            for proc in self._procs:
                proc.join(timeout=max(0.0, deadline - time.monotonic()))
        for proc in self._procs:
            if proc.is_alive():
                proc.terminate()
        for proc in self._procs:
            proc.join(timeout=5)
        if self._results is not None:
            self._results.put(("closed",))
        if self._reader is not None:
            self._reader.join(timeout=5)
        for q in (self._tasks, self._results):
            if q is not None:
                q.cancel_join_thread()
                q.close()

    def ready(self, timeout: float | None = None) -> bool:
        """Wait until every worker is ready for a task (or ``timeout`` s); True if they are."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while self._idle < self.workers and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(_POLL_S if left is None else min(left, _POLL_S))
            return self._idle >= self.workers and not self._closed

    def __enter__(self) -> StudyWorkers:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the reader thread -----------------------------------------------------------------
    def _read(self) -> None:
        while True:
            try:
                msg = self._results.get()
            except (EOFError, OSError):  # pragma: no cover - the queue went away at close
                return
            kind = msg[0]
            if kind == "closed":
                return
            if kind == "progress":
                run = self._run
                if run is not None:
                    run["progress"](msg[1])
                continue
            if kind == "took":
                with self._cond:
                    if self._run is not None:
                        self._run["running"][msg[1]] = msg[2]
                continue
            with self._cond:
                self._idle += 1  # a worker ready for its first task, or done with one
                if kind != "ready":
                    run = self._run
                    if run is not None:
                        run["outstanding"] -= 1
                        run["running"].pop(msg[1], None)
                        if kind == "done":
                            run["results"][msg[1]] = msg[2]
                        elif run["error"] is None:
                            exc = msg[2]
                            exc.add_note(f"In a study worker:\n{msg[3]}")
                            run["error"] = exc
                self._dispatch()
                self._cond.notify_all()

    def _dispatch(self) -> None:
        """Hand pending tasks to idle workers (called with the condition held)."""
        run = self._run
        if run is None or run["error"] is not None or self._closed:
            return
        while self._idle > 0 and run["pending"]:
            index, task = run["pending"].popleft()
            self._idle -= 1
            run["outstanding"] += 1
            self._tasks.put((index, run["fn"], task))

    # -- running ---------------------------------------------------------------------------
    def map(
        self,
        fn: Callable[[Any, Callable[[int], None]], Any],
        tasks: Sequence[Any],
        progress: Callable[[int], None] = lambda n: None,
    ) -> list[Any]:
        """``[fn(task, report) for task in tasks]``, run by the caller and the workers, in
        the order of ``tasks``; ``progress(n)`` gets every report (from any thread)."""
        lock = threading.Lock()

        def locked(n: int) -> None:
            with lock:
                progress(n)

        run: dict[str, Any] = {
            "fn": fn,
            "pending": deque(enumerate(tasks)),
            "results": {},
            "outstanding": 0,
            "running": {},
            "error": None,
            "progress": locked,
        }
        with self._cond:
            if self._closed:
                raise RuntimeError("These study workers are closed.")
            self._run = run
            self._dispatch()
        try:
            while True:
                with self._cond:
                    if run["error"] is not None or not run["pending"]:
                        break
                    index, task = run["pending"].popleft()
                run["results"][index] = fn(task, locked)
            self._wait(run)
            if run["error"] is not None:
                raise run["error"]
        except BaseException:
            self.close()  # another worker may still be running a task of this run
            raise
        finally:
            with self._cond:
                self._run = None
        return [run["results"][i] for i in range(len(tasks))]

    def _wait(self, run: dict[str, Any]) -> None:
        with self._cond:
            while run["outstanding"] > 0 and run["error"] is None:
                self._cond.wait(_POLL_S)
                busy = set(run["running"].values())
                dead = [p for p in self._procs if p.pid in busy and not p.is_alive()]
                if not any(p.is_alive() for p in self._procs):  # a task no one can take
                    dead = list(self._procs)
                if dead:
                    codes = ", ".join(f"pid {p.pid}, exit code {p.exitcode}" for p in dead)
                    run["error"] = RuntimeError(
                        f"A study worker died ({codes}) while running a task; run again with "
                        "--jobs 1 to run everything in this process."
                    )
