"""Diagnoses started over HTTP (``POST /wells/{well}/diagnosis``): background jobs with progress.

A job runs ``vfm diagnose --store <the service's store> --well W`` (the well beside the
other wells that run the same model and method; the well's own learning method replayed)
in a process of its own
(``python -m service.diagnosis``, never a fork after Zenoh opened), so it never holds the
engine's workers or the GIL: the child reads the well's stored history through
:func:`service.export.load_store` (a read-only connection), runs
:func:`vfm_core.jobs.diagnose.run_diagnosis` with a progress callback, and writes
``diagnosis.json`` and ``report.html`` with
:func:`~vfm_core.jobs.diagnose.write_diagnosis` into ``<store folder>/diagnoses/<job>/``.
When the service was fitted on a history file (``model.history``, ``model.history_until``),
that history goes in front of the store (:func:`~vfm_core.jobs.diagnose.with_history`) and
the replay starts at ``history_until``, where the service started: the diagnosis's baseline
is then the error the service recorded, not a fresh fit's.
Progress comes back as JSON lines on its stdout; its stderr goes to ``diagnose.log`` there.

One diagnosis runs at a time (a second request is refused with
:class:`~service.errors.Conflict`), and each has a wall-clock budget
(``http.diagnosis_budget_s``) after which its process is stopped and the job fails with a
sentence saying so. The last :data:`KEEP_JOBS` jobs are remembered: each job's folder holds
its record (``job.json``, :mod:`service.diagnosis_records`), from which the list is rebuilt
when the service starts again (a job that was running then comes back failed, saying so).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import secrets
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from service.config import Settings
from service.diagnosis_records import load_jobs, save_job
from service.engine.model_change import check_effect_modules
from service.errors import Conflict, InvalidRequest, Stopping
from vfm_core.errors import VFMError
from vfm_core.models import EFFECT_MODELS

__all__ = ["DiagnosisJobs", "Job", "MODELS", "KEEP_JOBS"]

logger = logging.getLogger("vfm.service.diagnosis")

#: base models the diagnosis takes: those effects extend
MODELS = EFFECT_MODELS
#: jobs remembered for GET /diagnosis/{job}
KEEP_JOBS = 20


@dataclass
class Job:
    """One diagnosis: its request, state (queued, running, done, failed), progress, result."""

    id: str
    well: str
    request: dict[str, Any]
    folder: Path
    state: str = "queued"
    fraction: float = 0.0
    text: str = "starting"
    error: str | None = None
    started: float = field(default_factory=time.time)
    finished: float | None = None

    def view(self) -> dict[str, Any]:
        """What ``GET /diagnosis/{job}`` answers (with the diagnosis once done)."""
        out: dict[str, Any] = {
            "job": self.id,
            "well": self.well,
            "request": self.request,
            "state": self.state,
            "progress": round(self.fraction, 4),
            "progress_text": self.text,
            "error": self.error,
            "elapsed_s": round((self.finished or time.time()) - self.started, 2),
            "diagnosis": None,
            "report": None,
        }
        if self.state == "done":
            out["diagnosis"] = json.loads((self.folder / "diagnosis.json").read_text("utf-8"))
            if (self.folder / "report.html").is_file():
                out["report"] = f"/diagnosis/{self.id}/report.html"
        return out


def _child(request: dict[str, Any]) -> None:
    """The job's process: load the well's history, diagnose, write; one JSON line per step."""

    def say(kind: str, fraction: float, text: str) -> None:
        print(json.dumps([kind, fraction, text]), flush=True)

    try:
        from vfm_core.runtime import configure

        configure(1)  # torch's threads, glibc's malloc
        from service.export import load_store
        from vfm_core.jobs.diagnose import pool_frame, run_diagnosis, stored_method, write_diagnosis

        say("progress", 0.0, "reading the stored history")
        pooled = request.get("pool", True)
        frame = load_store(request["store"], None if pooled else request["well"])
        if pooled:
            frame, note = pool_frame(frame, request["well"])
            say("progress", 0.0, note)
        method = request.get("method") or stored_method(frame, request["well"]) or "ol"
        split = request["split"]
        screen_split = None
        source: dict[str, Any] = {
            "kind": "store",
            "path": request["store"],
            "well": request["well"],
        }
        if request.get("history") and request.get("history_until"):
            from vfm_core.jobs.diagnose import with_history
            from vfm_core.observations import load_observations

            say("progress", 0.0, "reading the history the service was fitted on")
            history = load_observations(request["history"]).frame
            frame, history_split, note = with_history(frame, history, request["history_until"])
            say("progress", 0.0, note)
            split = split or history_split
            screen_split = "auto"  # identified where both sides span the operating range
            source.update(history=request["history"], history_until=str(history_split), note=note)
        diag = run_diagnosis(
            frame,
            request["model"],
            method=method,
            well=request["well"],
            split=split,
            screen_split=screen_split,
            candidates=request["candidates"],
            base_effects=request.get("base_effects") or [],
            suggest=request["suggest"],
            progress=lambda fraction, text: say("progress", float(fraction), str(text)),
            source=source,
        )
        say("progress", 0.99, "writing diagnosis.json and report.html")
        write_diagnosis(diag, request["folder"], report=request["report"])
        say("done", 1.0, diag.verdict)
    except VFMError as exc:
        say("failed", 0.0, str(exc))
    except Exception as exc:  # pragma: no cover - a bug: say what it was
        say("failed", 0.0, f"The diagnosis failed unexpectedly: {type(exc).__name__}: {exc}")


def _read(stream: IO[str], lines: queue.Queue[tuple[str, float, str]]) -> None:
    for line in stream:
        try:
            kind, fraction, text = json.loads(line)
        except (ValueError, TypeError):
            continue  # not ours (a library printing)
        lines.put((str(kind), float(fraction), str(text)))


class DiagnosisJobs:
    """The service's diagnosis jobs; see the module docstring."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.folder = Path(settings.store.path).resolve().parent / "diagnoses"
        self.budget_s = settings.http.diagnosis_budget_s
        self._lock = threading.Lock()
        self._jobs: dict[str, Job] = {}
        self._running: Job | None = None
        self._stopping = threading.Event()
        # the jobs of earlier runs, from their folders (service.diagnosis_records)
        self._jobs.update(load_jobs(self.folder, KEEP_JOBS, Job))

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def check(
        self,
        model: str,
        candidates: list[str] | None,
        split: str | None,
        base_effects: list[str] | None = None,
        base_from_model: bool = False,
    ) -> list[str] | None:
        """Refuse a bad request before any work (an unknown model or effect, a module not
        allowed). ``base_from_model``: the base effects are the well's own model's (set by
        the configuration or an allowed change), so their modules are not checked again."""
        if model not in MODELS:
            raise InvalidRequest(
                f"The diagnosis takes the model mm, hem or ham, not '{model}'; the effects "
                "found are then added to it (PUT /wells/{well}/model)."
            )
        from vfm_core.effects import resolve_effect, resolve_effects

        allowed = self.settings.model.effect_modules
        check_effect_modules(candidates or [], allowed, "candidate")
        if not base_from_model:
            check_effect_modules(base_effects or [], allowed, "base effect")
        try:
            for text in candidates or []:
                resolve_effect(text)
            resolve_effects(base_effects or [])  # (each, and none twice)
        except VFMError as exc:
            raise InvalidRequest(str(exc)) from None
        if split is not None:
            import pandas as pd

            try:
                pd.Timestamp(split)
            except ValueError:
                raise InvalidRequest(
                    f"split={split[:40]!r} is not a date; write it like 2019-01-01, or leave it "
                    "out for the default."
                ) from None
        return candidates

    def start(
        self,
        well: str,
        model: str = "mm",
        method: str | None = None,
        candidates: list[str] | None = None,
        split: str | None = None,
        suggest: bool = True,
        report: bool = True,
        base_effects: list[str] | None = None,
        base_from_model: bool = False,
        pool: bool = True,
    ) -> Job:
        """Start a diagnosis of ``well``'s stored history; Conflict while another runs.
        ``base_effects``: the effects already in the model (see :func:`run_diagnosis
        <vfm_core.jobs.diagnose.run_diagnosis>`); ``base_from_model``: they are the well's
        model's own (see :meth:`check`)."""
        checked = self.check(model, candidates, split, base_effects, base_from_model)
        if method is not None:
            from vfm_core.learning import parse_method

            try:
                parse_method(method)
            except VFMError as exc:
                raise InvalidRequest(str(exc)) from None
        if self._stopping.is_set():
            raise Stopping("The service is stopping; retry after it restarts.")
        with self._lock:
            busy = self._running
            if busy is not None:
                raise Conflict(
                    f"A diagnosis is already running (job {busy.id} of {busy.well}, "
                    f"{busy.fraction:.0%}: {busy.text}); one runs at a time, so wait for it "
                    f"(GET /diagnosis/{busy.id}) and start this one after."
                )
            job_id = secrets.token_hex(6)
            folder = self.folder / job_id
            request = {
                "model": model,
                "method": method,
                "candidates": checked,
                "base_effects": list(base_effects or []),
                "split": split,
                "suggest": suggest,
                "pool": pool,
            }
            job = Job(job_id, well, request, folder)
            self._jobs[job_id] = job
            while len(self._jobs) > KEEP_JOBS:
                self._jobs.pop(next(iter(self._jobs)))
            self._running = job
        child_request = {
            **request,
            "candidates": checked if checked is not None else _default_candidates(),
            "store": str(self.settings.store.path),
            # the history the service was fitted on: the replay starts where the service did
            "history": _history(self.settings),
            "history_until": _history_until(self.settings),
            "well": well,
            "folder": str(folder),
            "report": report,
        }
        threading.Thread(
            target=self._watch,
            args=(job, child_request),
            name=f"vfm-diagnosis-{job_id}",
            daemon=True,
        ).start()
        return job

    def _watch(self, job: Job, request: dict[str, Any]) -> None:
        job.folder.mkdir(parents=True, exist_ok=True)
        save_job(job)
        lines: queue.Queue[tuple[str, float, str]] = queue.Queue()
        proc: subprocess.Popen[str] | None = None
        finished_ok = False
        try:
            with (job.folder / "diagnose.log").open("w", encoding="utf-8") as log:
                proc = subprocess.Popen(
                    [sys.executable, "-m", "service.diagnosis", json.dumps(request)],
                    stdout=subprocess.PIPE,
                    stderr=log,
                    stdin=subprocess.DEVNULL,
                    text=True,
                    env={**os.environ, "PYTHONUNBUFFERED": "1"},
                )
            assert proc.stdout is not None
            threading.Thread(target=_read, args=(proc.stdout, lines), daemon=True).start()
            job.state = "running"
            deadline = time.monotonic() + self.budget_s
            while True:
                try:
                    kind, fraction, text = lines.get(timeout=0.2)
                except queue.Empty:
                    if self._stopping.is_set():
                        job.error = "The service stopped before the diagnosis finished."
                        break
                    if time.monotonic() > deadline:
                        job.error = (
                            f"The diagnosis took longer than its budget of {self.budget_s:g} s "
                            "(http.diagnosis_budget_s) and was stopped; give fewer candidates "
                            "or raise the budget."
                        )
                        break
                    if proc.poll() is not None and lines.empty():
                        job.error = (
                            f"The diagnosis process ended without an answer (exit code "
                            f"{proc.returncode}); see {job.folder / 'diagnose.log'}."
                        )
                        break
                    continue
                if kind == "progress":
                    job.fraction, job.text = fraction, text
                    continue
                if kind == "done":
                    job.fraction, job.text = 1.0, "done"
                    finished_ok = True
                else:
                    job.error = text
                break
        except Exception as exc:  # pragma: no cover - spawning failed
            job.error = f"The diagnosis could not start: {exc}"
        finally:
            # the process goes first; then, in one step, the job shows its end and frees the
            # slot, so a client that sees "done" may start the next diagnosis at once
            if proc is not None:
                if proc.poll() is None:
                    proc.terminate()
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:  # pragma: no cover
                    proc.kill()
                    proc.wait(5)
                if proc.stdout is not None:
                    proc.stdout.close()
            with self._lock:
                job.finished = time.time()
                job.state = "done" if finished_ok else "failed"
                self._running = None
            save_job(job)
            if finished_ok:
                logger.info("Diagnosis %s of %s done.", job.id, job.well)
            else:
                logger.warning("Diagnosis %s of %s failed: %s", job.id, job.well, job.error)

    def stop(self, timeout: float = 10.0) -> None:
        """The service stops: end a running diagnosis."""
        self._stopping.set()
        deadline = time.monotonic() + timeout
        while self._running is not None and time.monotonic() < deadline:
            time.sleep(0.05)


def _history(settings: Settings) -> str | None:
    path = settings.model.history
    return str(path) if path is not None and Path(path).is_file() else None


def _history_until(settings: Settings) -> str | None:
    until = settings.model.history_until
    return None if until is None else until.isoformat()


def _default_candidates() -> list[str]:
    from vfm_core.jobs.diagnose import DEFAULT_CANDIDATES

    return [c if isinstance(c, str) else c.name for c in DEFAULT_CANDIDATES]


if __name__ == "__main__":  # the job's process: python -m service.diagnosis '<request JSON>'
    _child(json.loads(sys.argv[1]))
