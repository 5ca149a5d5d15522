"""Diagnosis jobs that outlive a restart: each job's record in its own folder.

:class:`service.diagnosis.DiagnosisJobs` keeps its jobs in memory, and each job writes its
results into ``<store folder>/diagnoses/<job>/``. :func:`save_job` writes the job's record
there as ``job.json`` (its id, well, request, state, progress, error, start and end, epoch
s), atomically (a temporary file renamed over the old one), when the job starts and when it
ends. At start, :func:`load_jobs` rebuilds the list from those folders, oldest first, at
most ``keep`` (the newest):

* a job that was ``queued`` or ``running`` when the service stopped is ``failed``, with a
  sentence saying so (its process ended with the service);
* a folder from before records were written, with a ``diagnosis.json`` but no
  ``job.json``, is a ``done`` job rebuilt from its diagnosis (well, model, method; its
  times are the file's);
* a folder with neither, or a record that cannot be read, is left out (and logged).

Records hold plain JSON (no pickle), so a record from another version of the service
cannot run code; a field it lacks takes the job's default.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

__all__ = ["RECORD", "save_job", "load_jobs", "record_of"]

logger = logging.getLogger("vfm.service.diagnosis")

#: the record's file name in the job's folder
RECORD = "job.json"
#: a job id as DiagnosisJobs makes them (secrets.token_hex), and no other folder name
_JOB_ID = re.compile(r"[0-9a-f]{6,64}")
#: the fields of a record, as the job keeps them
_FIELDS = (
    "id",
    "well",
    "request",
    "state",
    "fraction",
    "text",
    "error",
    "started",
    "finished",
)


class JobLike(Protocol):
    """What a record is made from (:class:`service.diagnosis.Job`)."""

    id: str
    well: str
    request: dict[str, Any]
    folder: Path
    state: str
    fraction: float
    text: str
    error: str | None
    started: float
    finished: float | None


J = TypeVar("J")


def record_of(job: JobLike) -> dict[str, Any]:
    """The job's record: its fields, JSON-ready (the folder is where the record lies)."""
    return {name: getattr(job, name) for name in _FIELDS}


def save_job(job: JobLike) -> None:
    """Write ``job.json`` into the job's folder (made if missing); never raises: a record
    that cannot be written costs the job its place in the list after a restart, nothing
    more, and is logged."""
    try:
        job.folder.mkdir(parents=True, exist_ok=True)
        tmp = job.folder / f".{RECORD}.tmp"
        tmp.write_text(json.dumps(record_of(job), allow_nan=False), encoding="utf-8")
        os.replace(tmp, job.folder / RECORD)
    except (OSError, TypeError, ValueError) as exc:
        logger.warning("The record of diagnosis %s was not written: %s", job.id, exc)


def load_jobs(folder: Path, keep: int, make: Callable[..., J]) -> dict[str, J]:
    """The jobs recorded under ``folder`` (``<store folder>/diagnoses``), the newest
    ``keep``, oldest first, each made with ``make(**fields, folder=...)`` (the job class)."""
    if not folder.is_dir():
        return {}
    found: list[dict[str, Any]] = []
    for sub in folder.iterdir():
        if not (sub.is_dir() and _JOB_ID.fullmatch(sub.name)):
            continue
        fields = _read(sub)
        if fields is not None:
            found.append(fields)
    found.sort(key=lambda f: (float(f["started"]), f["id"]))
    return {f["id"]: make(**f) for f in found[-keep:]} if keep > 0 else {}


def _read(sub: Path) -> dict[str, Any] | None:
    """One folder's job fields, or None (logged) when it holds none that can be read."""
    record = sub / RECORD
    try:
        if record.is_file():
            data = json.loads(record.read_text("utf-8"))
            fields = {k: data[k] for k in _FIELDS if k in data}
            if fields.get("id") != sub.name or not isinstance(fields.get("well"), str):
                raise ValueError("its id or well is missing or not its folder's")
            if not isinstance(fields.get("request", {}), dict):
                raise ValueError("its request is not an object")
            fields["started"] = float(fields.get("started", record.stat().st_mtime))
            if fields.get("state") in ("queued", "running"):
                fields["state"] = "failed"
                fields["error"] = (
                    "The service stopped before the diagnosis finished "
                    f"({float(fields.get('fraction', 0.0)):.0%} done: "
                    f"{fields.get('text', '')}); start it again with POST "
                    f"/wells/{fields['well']}/diagnosis."
                )
                fields["finished"] = fields.get("finished") or record.stat().st_mtime
            return {**fields, "folder": sub}
        diagnosis = sub / "diagnosis.json"
        if diagnosis.is_file():  # a job from before records were written
            data = json.loads(diagnosis.read_text("utf-8"))
            source = data.get("source") or {}
            well = source.get("well") if isinstance(source, dict) else None
            if not isinstance(well, str):
                raise ValueError("its diagnosis.json names no well (source.well)")
            when = diagnosis.stat().st_mtime
            return {
                "id": sub.name,
                "well": well,
                "request": {
                    "model": data.get("model"),
                    "method": data.get("method"),
                    "base_effects": data.get("base_effects", []),
                    "split": data.get("split"),
                },
                "state": "done",
                "fraction": 1.0,
                "text": "done",
                "started": when,
                "finished": when,
                "folder": sub,
            }
    except (OSError, ValueError, TypeError, KeyError) as exc:
        logger.warning("The diagnosis folder %s is left out of the job list: %s", sub, exc)
        return None
    return None
