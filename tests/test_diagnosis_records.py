"""Diagnosis jobs outlive a restart: their records (``job.json``) in their folders.

The record module (:mod:`service.diagnosis_records`) round-trips a real
:class:`service.diagnosis.Job`; a job that was running when the service stopped comes back
failed with a sentence; a folder from before records has its job rebuilt from its
``diagnosis.json``; unreadable records and foreign folders are left out; only the newest
are kept. Then the service's own job list: a job run by one :class:`DiagnosisJobs` is
known, with the same answer, to the next one made on the same store (a restart).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.diagnosis import KEEP_JOBS, DiagnosisJobs, Job
from service.diagnosis_records import RECORD, load_jobs, save_job
from service.testing import loopback_settings, wait_until

pytestmark = pytest.mark.timeout(120)


def _job(folder: Path, job_id: str, started: float, **fields: object) -> Job:
    job = Job(job_id, "W01", {"model": "mm", "method": "ol"}, folder / job_id, started=started)
    for name, value in fields.items():
        setattr(job, name, value)
    return job


def test_a_record_round_trips_a_job(tmp_path: Path) -> None:
    done = _job(tmp_path, "a1b2c3d4e5f6", 100.0, state="failed", error="It failed.")
    done.finished = 130.5
    done.fraction, done.text = 0.25, "fitting"
    save_job(done)
    assert (done.folder / RECORD).is_file()
    assert not list(done.folder.glob(".*.tmp"))  # written atomically, nothing left behind
    back = load_jobs(tmp_path, KEEP_JOBS, Job)
    assert list(back) == [done.id]
    job = back[done.id]
    assert job.view() == done.view()
    assert (job.folder, job.started, job.finished) == (done.folder, 100.0, 130.5)


def test_a_job_cut_by_a_restart_comes_back_failed(tmp_path: Path) -> None:
    running = _job(tmp_path, "0123456789ab", 50.0, state="running", fraction=0.4, text="scoring")
    save_job(running)
    job = load_jobs(tmp_path, KEEP_JOBS, Job)[running.id]
    assert job.state == "failed" and job.finished is not None
    assert job.error is not None and job.error.endswith(".")
    assert "stopped before the diagnosis finished" in job.error and "40%" in job.error
    assert "POST /wells/W01/diagnosis" in job.error
    view = job.view()
    assert view["diagnosis"] is None and view["report"] is None


def test_an_older_folder_is_rebuilt_from_its_diagnosis(tmp_path: Path) -> None:
    folder = tmp_path / "fedcba987654"
    folder.mkdir()
    diagnosis = {
        "format": "vfm-diagnosis/3",
        "model": "mm",
        "method": "ol",
        "base_effects": [],
        "split": "2016-07-01T00:00:00+00:00",
        "source": {"kind": "store", "path": "/x/store.sqlite", "well": "W07"},
        "verdict": {"text": "No effect found."},
    }
    (folder / "diagnosis.json").write_text(json.dumps(diagnosis), "utf-8")
    (folder / "report.html").write_text("<html></html>", "utf-8")
    job = load_jobs(tmp_path, KEEP_JOBS, Job)["fedcba987654"]
    assert (job.well, job.state, job.request["model"]) == ("W07", "done", "mm")
    view = job.view()
    assert view["diagnosis"] == diagnosis
    assert view["report"] == "/diagnosis/fedcba987654/report.html"


def test_unreadable_and_foreign_folders_are_left_out(tmp_path: Path) -> None:
    good = _job(tmp_path, "aaaaaaaaaaaa", 1.0, state="done")
    save_job(good)
    (tmp_path / "bbbbbbbbbbbb").mkdir()
    (tmp_path / "bbbbbbbbbbbb" / RECORD).write_text("{not json", "utf-8")
    (tmp_path / "cccccccccccc").mkdir()  # a record naming another folder's job
    other = {"id": "dddddddddddd", "well": "W01", "state": "done", "started": 2.0}
    (tmp_path / "cccccccccccc" / RECORD).write_text(json.dumps(other), "utf-8")
    (tmp_path / "notes").mkdir()  # not a job id
    (tmp_path / "notes" / RECORD).write_text(json.dumps(other | {"id": "notes"}), "utf-8")
    (tmp_path / "eeeeeeeeeeee").mkdir()  # a job whose process never wrote anything
    assert list(load_jobs(tmp_path, KEEP_JOBS, Job)) == ["aaaaaaaaaaaa"]
    assert load_jobs(tmp_path / "missing", KEEP_JOBS, Job) == {}


def test_the_newest_are_kept_oldest_first(tmp_path: Path) -> None:
    ids = [f"{i:012x}" for i in range(6)]
    for i, job_id in enumerate(reversed(ids)):  # written in another order than started
        save_job(_job(tmp_path, job_id, 1000.0 - i, state="done"))
    back = load_jobs(tmp_path, 4, Job)
    assert list(back) == [ids[2], ids[3], ids[4], ids[5]]


def test_the_service_job_list_survives_a_restart(tmp_path: Path) -> None:
    """A job that ran (and failed: the store is empty) under one DiagnosisJobs is known,
    with the same answer, to the next one made on the same store, as after a restart."""
    settings = loopback_settings(tmp_path)
    first = DiagnosisJobs(settings)
    job = first.start("W01", model="mm", method="ol")
    wait_until(lambda: job.state in ("done", "failed"), 90, "the diagnosis job to end")
    assert job.state == "failed" and job.error
    record = job.folder / RECORD

    def recorded_end() -> bool:  # written right after the state changes
        try:
            return json.loads(record.read_text("utf-8"))["state"] == job.state
        except (OSError, ValueError, KeyError):
            return False

    wait_until(recorded_end, 10, "the job's record of its end")
    restarted = DiagnosisJobs(settings)
    again = restarted.get(job.id)
    assert again is not None, "the job list was not rebuilt from the job folders"
    assert again.view() == job.view()
    first.stop()
    restarted.stop()
