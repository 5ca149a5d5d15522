"""The study's worker processes (vfm_core.jobs.workers) and `vfm evaluate --jobs`.

A worker is spawned and imports the study before it takes a task (a few seconds), so each
test that needs one starts it once. The tasks below wait for each other through marker
files, so that which process runs which task does not depend on timing."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pandas as pd
import pytest

from vfm_core.cli import main
from vfm_core.jobs.evaluate import run_study
from vfm_core.jobs.workers import StudyWorkers
from vfm_core.simulate import simulate_field

WAIT_S = 120.0


def _wait_for(path: Path) -> None:
    deadline = time.monotonic() + WAIT_S
    while not path.exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} never appeared")
        time.sleep(0.02)


def rendezvous(task: dict, report) -> tuple[int, int]:
    """Task 0 waits until another process has run task 1; every task reports progress."""
    folder = Path(task["folder"])
    if task["i"] == 0:
        _wait_for(folder / "1.done")
    if task["i"] == 1:
        if task.get("fail") == "raise":
            (folder / "1.done").write_text("")
            raise ValueError("task 1 cannot go on: a bad value")
        if task.get("fail") == "die":
            (folder / "1.done").write_text("")
            os.kill(os.getpid(), signal.SIGKILL)
        (folder / "1.done").write_text(str(os.getpid()))
    report(task["i"] + 1)
    return task["i"] * task["i"], os.getpid()


def test_the_caller_and_a_worker_share_the_tasks_and_results_keep_their_order(tmp_path) -> None:
    seen: list[int] = []
    tasks = [{"i": i, "folder": str(tmp_path)} for i in range(6)]
    with StudyWorkers(1, threads=1) as workers:
        out = workers.map(rendezvous, tasks, seen.append)
        # the same workers serve a second call (vfm evaluate's second case)
        again = workers.map(rendezvous, [{"i": 5, "folder": str(tmp_path)}])
    assert [value for value, _ in out] == [i * i for i in range(6)]
    pids = [pid for _, pid in out]
    assert pids[0] == os.getpid()  # the caller does not wait for the worker to start
    assert pids[1] != os.getpid()  # task 0 could only end once another process ran task 1
    assert sum(seen) == sum(i + 1 for i in range(6))  # every report reached the caller
    assert again[0][0] == 25


def test_an_error_in_a_worker_is_raised_in_the_caller_with_its_traceback(tmp_path) -> None:
    tasks = [{"i": i, "folder": str(tmp_path), "fail": "raise"} for i in range(3)]
    with (
        StudyWorkers(1, threads=1) as workers,
        pytest.raises(ValueError, match="bad value") as info,
    ):
        workers.map(rendezvous, tasks)
    notes = "".join(getattr(info.value, "__notes__", []))
    assert "In a study worker" in notes and "rendezvous" in notes


def test_a_worker_that_dies_ends_the_run_with_a_sentence(tmp_path) -> None:
    tasks = [{"i": i, "folder": str(tmp_path), "fail": "die"} for i in range(3)]
    with StudyWorkers(1, threads=1) as workers, pytest.raises(RuntimeError, match="died") as info:
        workers.map(rendezvous, tasks)
    assert "--jobs 1" in str(info.value) and str(-signal.SIGKILL) in str(info.value)


def test_a_study_in_two_processes_gives_the_results_of_one() -> None:
    frame = simulate_field(wells=2, years=1.2, seed=5, start="2018-06-01").observations
    kwargs = dict(
        models=["last", "mm", "lr"],
        methods=["ol", "pbl:60d"],
        targets="all",
        outages="30d",
        progress=False,
    )
    alone = run_study(frame, **kwargs)
    with StudyWorkers(1, threads=1) as workers:
        assert workers.ready(WAIT_S)  # so the worker takes the first model for certain
        shared = run_study(frame, workers=workers, **kwargs)
    assert shared.records == alone.records and shared.summary == alone.summary
    pd.testing.assert_frame_equal(shared.predictions, alone.predictions)
    pd.testing.assert_frame_equal(shared.outage_predictions, alone.outage_predictions)
    key = [(r["model"], r["method"], r.get("outage"), r["retrains"]) for r in alone.runs]
    assert [(r["model"], r["method"], r.get("outage"), r["retrains"]) for r in shared.runs] == key
    assert shared.updates == alone.updates


def test_evaluate_jobs_option(tmp_path, capsys) -> None:
    data = tmp_path / "field.parquet"
    simulate_field(wells=2, years=1.2, seed=5, start="2018-06-01").observations.to_parquet(data)
    args = ["evaluate", str(data), "--models", "last,mm", "--methods", "ol", "--no-report"]
    assert main([*args, "--out", str(tmp_path / "one"), "--jobs", "1", "--quiet"]) == 0
    assert "processes" not in capsys.readouterr().out
    assert main([*args, "--out", str(tmp_path / "two"), "--jobs", "2", "--quiet"]) == 0
    assert "Running models in 2 processes" in capsys.readouterr().out
    one, two = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("one", "two"))
    assert one["records"] == two["records"]
    with pytest.raises(SystemExit):
        main([*args, "--out", str(tmp_path / "bad"), "--jobs", "0"])
    assert "not a positive number of processes" in capsys.readouterr().err


def test_close_lets_idle_workers_end_by_themselves() -> None:
    """Workers that are ready and idle are told to end, not terminated: close() returns at
    once and they exit by themselves (terminated, they would exit with -15)."""
    workers = StudyWorkers(2, threads=1).start()
    assert workers.ready(WAIT_S)
    started = time.monotonic()
    workers.close()
    took = time.monotonic() - started
    assert [p.exitcode for p in workers._procs] == [0, 0]
    # a worker that did not end by itself would be terminated after 10 s (and exit -15);
    # ending takes a torch process seconds on a loaded machine
    assert took < 10.0, f"close took {took:.1f} s"


def hang_in_worker(task: dict, report) -> None:
    """In a worker, a task that never ends by itself; in the caller, one that fails once the
    worker's has started."""
    folder = Path(task["folder"])
    if os.getpid() != task["caller"]:
        (folder / "started").write_text(str(os.getpid()))
        time.sleep(WAIT_S)
        return
    _wait_for(folder / "started")
    raise ValueError("the caller's task failed while a worker's was running")


def test_an_error_in_the_caller_stops_a_worker_in_the_middle_of_a_task(tmp_path) -> None:
    """An error (or Ctrl-C) while a worker runs a long task: the worker is terminated, the
    caller does not wait for the task."""
    tasks = [{"caller": os.getpid(), "folder": str(tmp_path)} for i in range(2)]
    workers = StudyWorkers(1, threads=1)
    with workers, pytest.raises(ValueError, match="the caller's task failed"):
        assert workers.ready(WAIT_S)
        started = time.monotonic()
        workers.map(hang_in_worker, tasks)
    took = time.monotonic() - started
    assert took < 15.0, f"the run took {took:.1f} s to stop"
    assert [p.exitcode for p in workers._procs] == [-signal.SIGTERM]


def test_close_while_the_workers_import_terminates_them() -> None:
    """An early error (a missing file, say) closes workers that are still importing: they
    are terminated at once, not waited for."""
    workers = StudyWorkers(2, threads=1).start()
    started = time.monotonic()
    workers.close()
    assert time.monotonic() - started < 5.0
    assert all(not p.is_alive() for p in workers._procs)
