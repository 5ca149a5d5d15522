"""Worker processes that share a list of tasks with the process that asks for them.

``vfm evaluate --jobs N`` runs the study's model groups N at a time: the calling process
takes groups itself while N - 1 workers of a :class:`~concurrent.futures.ProcessPoolExecutor`
start (spawned, never forked: torch, tqdm and numba hold threads; the executor's
``initializer`` imports the study and warms the kernels, a few seconds). A worker gets a
group only once it is ready, so a small study never waits for a worker to start: at worst
the caller ran everything alone. The workers live until :meth:`StudyWorkers.close`, so the
two cases of one ``vfm evaluate`` share them.

A task's function must be a module-level callable ``fn(task, report)``; ``report(n)`` adds
``n`` to the caller's progress. Tasks and results travel pickled between this process and
its own workers only (nothing from outside is unpickled). An exception in a task is raised
again in the caller, with the worker's traceback as a note; a worker that dies (killed, out
of memory) ends the run with an error naming its exit code. Ctrl-C reaches the caller only
(workers ignore SIGINT) and the caller stops the workers.

What the executor does not give, and this module adds: the readiness of each worker and
the progress of a running task (a message queue handed to the initializer), the caller
taking tasks itself, and, because Python 3.11's executor can neither terminate its workers
(``shutdown`` waits for a running task; ``terminate_workers`` came in 3.14) nor say which
worker died with which exit code, the handles of the processes it spawned (read from
:func:`multiprocessing.active_children` as they start).
"""

from __future__ import annotations

import functools
import multiprocessing as mp
import os
import signal
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

__all__ = ["StudyWorkers", "usable_cpus"]

#: a worker sends its progress at most this often, s
_PROGRESS_EVERY_S = 0.25
#: how often the caller checks on its run while it waits, s
_POLL_S = 0.5
#: a worker's end of the message queue to the caller (set by :func:`_init_worker`)
_messages: Any = None


def usable_cpus() -> int:
    """CPUs this process may run on (its affinity where the system tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


# -- in a worker -----------------------------------------------------------------------------
def _init_worker(messages: Any, threads: int, preload: tuple[str, ...]) -> None:
    """The executor's initializer: import what the tasks need, then say it is ready."""
    global _messages
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller handles Ctrl-C and stops us
    import importlib

    from vfm_core.runtime import configure

    configure(threads)
    for name in preload:
        importlib.import_module(name)
    from vfm_core.learning import kernels

    kernels.warm()
    _messages = messages
    messages.put(("ready", os.getpid()))


def _start() -> None:
    """A first task that makes the executor spawn a worker (it spawns one per submission)."""


def _run_task(fn: Callable[[Any, Callable[[int], None]], Any], index: int, task: Any) -> tuple:
    """Run one task in a worker: ``("done", out)`` or ``("error", exc, traceback)``; its
    progress, then ``finished``, go to the caller's message queue before the result does."""
    _messages.put(("took", index, os.getpid()))
    pending = [0, time.monotonic()]

    def report(n: int) -> None:
        pending[0] += n
        now = time.monotonic()
        if now - pending[1] >= _PROGRESS_EVERY_S:
            _messages.put(("progress", pending[0]))
            pending[0], pending[1] = 0, now

    try:
        answer: tuple = ("done", fn(task, report))
    except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
        answer = ("error", _portable(exc), traceback.format_exc())
    if pending[0]:
        _messages.put(("progress", pending[0]))
    _messages.put(("finished", index))
    return answer


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a RuntimeError with its text."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc


# -- in the caller ---------------------------------------------------------------------------
class _Run:
    """One :meth:`StudyWorkers.map` call: its tasks, results and progress."""

    def __init__(self, fn: Callable, tasks: Sequence[Any], progress: Callable[[int], None]):
        self.fn = fn
        self.pending: deque[tuple[int, Any]] = deque(enumerate(tasks))
        self.results: dict[int, Any] = {}
        self.futures: dict[int, Future] = {}
        #: tasks whose worker said ``finished`` (their progress has all arrived)
        self.finished: set[int] = set()
        self.outstanding = 0
        #: index -> pid of the worker running it
        self.running: dict[int, int] = {}
        self.error: BaseException | None = None
        self.progress = progress


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
        self._executor: ProcessPoolExecutor | None = None
        self._procs: list[Any] = []
        self._messages: Any = None
        self._reader: threading.Thread | None = None
        self._cond = threading.Condition()
        self._idle = 0
        self._ready: set[int] = set()
        self._closed = False
        self._run: _Run | None = None

    # -- life cycle ------------------------------------------------------------------------
    def start(self) -> StudyWorkers:
        if self._executor is not None or self.workers == 0:
            return self
        ctx = mp.get_context("spawn")
        self._messages = ctx.Queue()
        self._executor = ProcessPoolExecutor(
            self.workers,
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(self._messages, self._threads, self._preload),
        )
        before = {p.pid for p in mp.active_children()}
        for _ in range(self.workers):
            self._executor.submit(_start)
        self._procs = [p for p in mp.active_children() if p.pid not in before]
        self._reader = threading.Thread(target=self._read, name="vfm-study-results", daemon=True)
        self._reader.start()
        return self

    def close(self) -> None:
        """Stop the workers: idle ones are told to end; when one is still importing or a
        task is still running (an error, Ctrl-C), they are all terminated."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            busy = self._run is not None and self._run.outstanding > 0
            starting = len(self._ready) < self.workers
            self._cond.notify_all()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            if busy or starting:  # the executor then ends the others itself
                for proc in self._procs:
                    proc.terminate()
            deadline = time.monotonic() + 10.0
            for proc in self._procs:
                proc.join(timeout=max(0.0, deadline - time.monotonic()))
            for proc in self._procs:
                if proc.is_alive():
                    proc.terminate()
                    proc.join(timeout=5)
        if self._messages is not None:
            self._messages.put(("closed",))
        if self._reader is not None:
            self._reader.join(timeout=5)
        if self._messages is not None:
            self._messages.cancel_join_thread()
            self._messages.close()

    def ready(self, timeout: float | None = None) -> bool:
        """Wait until every worker is ready for a task (or ``timeout`` s); True if they are."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while len(self._ready) < self.workers and not self._closed:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(_POLL_S if left is None else min(left, _POLL_S))
            return len(self._ready) >= self.workers and not self._closed

    def __enter__(self) -> StudyWorkers:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the reader thread and the executor's callbacks ------------------------------------
    def _read(self) -> None:
        while True:
            try:
                msg = self._messages.get()
            except (EOFError, OSError):  # pragma: no cover - the queue went away at close
                return
            kind = msg[0]
            if kind == "closed":
                return
            run = self._run
            if kind == "progress":
                if run is not None:
                    run.progress(msg[1])
                continue
            with self._cond:
                if kind == "took" and run is not None:
                    run.running[msg[1]] = msg[2]
                elif kind in ("ready", "finished"):
                    self._idle += 1  # a worker ready for its first task, or done with one
                    if kind == "ready":
                        self._ready.add(msg[1])
                    elif run is not None:
                        run.finished.add(msg[1])
                        self._settle(run, msg[1])
                    self._dispatch()
                self._cond.notify_all()

    def _on_done(self, run: _Run, index: int, future: Future) -> None:
        with self._cond:
            self._settle(run, index)
            self._cond.notify_all()

    def _settle(self, run: _Run, index: int) -> None:
        """Take a task's result once both its future and its last message are in (called
        with the condition held)."""
        future = run.futures.get(index)
        if future is None or not future.done() or index in run.results:
            return
        failed = future.cancelled() or future.exception() is not None
        if not failed and index not in run.finished:
            return  # the result came before the task's last progress: wait for it
        run.outstanding -= 1
        run.running.pop(index, None)
        if failed:
            if run.error is None:
                run.error = self._death(run, future)
            run.results[index] = None
            return
        answer = future.result()
        if answer[0] == "done":
            run.results[index] = answer[1]
        else:
            run.results[index] = None
            if run.error is None:
                exc = answer[1]
                exc.add_note(f"In a study worker:\n{answer[2]}")
                run.error = exc

    def _death(self, run: _Run, future: Future) -> BaseException:
        """The error for a task that no worker finished: a worker died (the executor then
        ends the others, with SIGTERM)."""
        if future.cancelled():
            return RuntimeError("A study task was cancelled because the workers are closing.")
        busy = set(run.running.values())
        dead: list[Any] = []
        deadline = time.monotonic() + 2.0  # its pipe closes a moment before it can be reaped
        while not dead and time.monotonic() < deadline:
            dead = [p for p in self._procs if p.pid in busy and p.exitcode is not None]
            dead = dead or [p for p in self._procs if p.exitcode not in (None, -signal.SIGTERM)]
            time.sleep(0.0 if dead else 0.02)
        codes = ", ".join(f"pid {p.pid}, exit code {p.exitcode}" for p in dead) or "unknown"
        error = RuntimeError(
            f"A study worker died ({codes}) while running a task; run again with "
            "--jobs 1 to run everything in this process."
        )
        error.__cause__ = future.exception()
        return error

    def _dispatch(self) -> None:
        """Hand pending tasks to idle workers (called with the condition held)."""
        run = self._run
        if run is None or run.error is not None or self._closed or self._executor is None:
            return
        while self._idle > 0 and run.pending:
            index, task = run.pending.popleft()
            try:
                future = self._executor.submit(_run_task, run.fn, index, task)
            except BrokenProcessPool as exc:
                run.pending.appendleft((index, task))
                run.error = RuntimeError(
                    "The study workers are gone (one died); run again with --jobs 1 to run "
                    f"everything in this process ({exc})."
                )
                return
            self._idle -= 1
            run.outstanding += 1
            run.futures[index] = future
            future.add_done_callback(functools.partial(self._on_done, run, index))

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

        run = _Run(fn, tasks, locked)
        with self._cond:
            if self._closed:
                raise RuntimeError("These study workers are closed.")
            self._run = run
            self._dispatch()
        try:
            while True:
                with self._cond:
                    if run.error is not None or not run.pending:
                        break
                    index, task = run.pending.popleft()
                run.results[index] = fn(task, locked)
            with self._cond:
                while run.outstanding > 0 and run.error is None:
                    self._cond.wait(_POLL_S)
            if run.error is not None:
                raise run.error
        except BaseException:
            self.close()  # another worker may still be running a task of this run
            raise
        finally:
            with self._cond:
                self._run = None
        return [run.results[i] for i in range(len(tasks))]
