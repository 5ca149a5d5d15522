"""``vfm replay``: the command line, pacing, scoring and its errors, against a real service."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from replay.replayer import ReplayError, replay_frame
from service.app import running
from service.testing import loopback_settings
from vfm_core.cli import main
from vfm_core.errors import ConfigError, DataError
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(180)

SPLIT = "2016-10-01"


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Any, Path, pd.DataFrame]]:
    folder = tmp_path_factory.mktemp("replay")
    frame = validate_frame(simulate_field(wells=1, years=1, seed=0).observations).frame
    data = folder / "field.csv"
    frame.to_csv(data, index=False)
    settings = loopback_settings(
        folder, model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT}
    )
    with running(settings) as svc:
        yield svc, data, frame


def test_cli_prints_mape_per_well_and_overall(
    served: tuple[Any, Path, pd.DataFrame], capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    svc, data, frame = served
    out = tmp_path / "scored.parquet"
    code = main(
        [
            "replay",
            str(data),
            "--connect",
            svc.locators[0],
            "--start",
            SPLIT,
            "--max",
            "--quiet",
            "--idle-timeout",
            "5",  # a loaded machine (CI at load 6, 2026-11-26) stalled the service past 1 s
            "--out",
            str(out),
        ]
    )
    text = capsys.readouterr().out
    assert code == 0, text
    n = int((frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")).sum())
    assert f"Replayed {n:,} rows" in text
    assert "Predictions: " + f"{n:,} received; 0 sample(s) got none" in text
    assert "W01" in text and "all" in text and "MAPE" in text
    scored = pd.read_parquet(out)
    assert len(scored) == int(
        ((frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")) & (frame["source"] != "")).sum()
    )
    assert scored["predicted"].notna().all()


def test_speed_paces_the_stream(served: tuple[Any, Path, pd.DataFrame]) -> None:
    svc, _, frame = served
    # ten days of data at 864,000 x real time: about one second; a year on, after every
    # row the other tests sent (rows the service has seen are refused as "time going
    # backwards", and the replay would wait out its patience for a first answer)
    rows = frame[
        (frame["time"] >= pd.Timestamp("2016-12-01", tz="UTC"))
        & (frame["time"] < pd.Timestamp("2016-12-11", tz="UTC"))
    ]
    rows = rows.assign(time=rows["time"] + pd.Timedelta(days=366))
    span = (rows["time"].iloc[-1] - rows["time"].iloc[0]).total_seconds()
    result = replay_frame(
        rows, connect=svc.locators, speed=864_000.0, progress=False, idle_timeout=1.0
    )
    # the sending alone takes span/speed; waiting for the last answers adds a little
    assert result.elapsed_s >= span / 864_000.0 * 0.95
    assert result.samples_sent == len(rows)
    assert result.predictions_received == result.samples_sent  # answered, not waited out


def test_no_service_is_a_clear_error() -> None:
    with pytest.raises(ReplayError, match="No service subscribes to vfm/W01/sensors after 1 s"):
        frame = validate_frame(simulate_field(wells=1, years=1, seed=0).observations).frame
        replay_frame(
            frame.iloc[:10], connect=["tcp/127.0.0.1:9"], match_timeout=1.0, progress=False
        )


def test_bad_arguments() -> None:
    frame = validate_frame(simulate_field(wells=1, years=1, seed=0).observations).frame
    with pytest.raises(DataError, match="No rows to replay on or after 2030-01-01"):
        replay_frame(frame, start="2030-01-01", progress=False)
    with pytest.raises(ConfigError, match="--start 'soon' is not a date"):
        replay_frame(frame, start="soon", progress=False)
    with pytest.raises(ConfigError, match="--speed must be a positive number"):
        replay_frame(frame, speed=0.0, progress=False)
    with pytest.raises(ConfigError, match="invalid"):
        replay_frame(frame, prefix="vfm/*", progress=False)


def test_cli_error_exit_code(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    code = main(["replay", str(tmp_path / "missing.parquet"), "--quiet"])
    assert code == 2
    assert "does not exist" in capsys.readouterr().err


def test_the_summary_names_the_samples_that_got_no_prediction() -> None:
    """A replay whose samples got no prediction names the first few (well and time) and
    counts the rest, so that the user can look them up in the service's log or store."""
    from replay.replayer import MISSING_SHOWN, ReplayResult

    t0 = pd.Timestamp("2017-03-01T06:00:00Z").value
    lacking = [("W02", t0 + k * 3_600 * 10**9) for k in range(5)]
    result = ReplayResult(
        start=None, rows=10, samples_sent=10, measurements_sent=0, predictions_received=5,
        missing=len(lacking), elapsed_s=1.0, scored=pd.DataFrame(),
        missing_samples=lacking[:MISSING_SHOWN],
    )  # fmt: skip
    text = result.summary()
    assert "5 sample(s) got none" in text
    # not "lost": a busy service answers later (walk57: a loaded machine, 2.6 s retrains)
    assert "was lost" not in text and "within --idle-timeout (3 s)" in text
    assert "Without a prediction: W02 at 2017-03-01T06:00:00Z, W02 at 2017-03-01T07:00:00Z" in text
    assert text.count("W02 at ") == MISSING_SHOWN and "and 2 more." in text
    complete = ReplayResult(None, 10, 10, 0, 10, 0, 1.0, pd.DataFrame())
    assert "Without a prediction" not in complete.summary()


def _answer_later(bus: Any, well: str, times_ns: list[int], after_s: float) -> threading.Thread:
    """Publish a prediction for each of ``times_ns`` after ``after_s`` s (a busy service)."""

    def publish() -> None:
        time.sleep(after_s)
        for t in times_ns:
            when = pd.Timestamp(t, tz="UTC").isoformat()
            bus.publish(well, json.dumps({"time": when, "q_total": 100.0}).encode())

    thread = threading.Thread(target=publish, daemon=True)
    thread.start()
    return thread


def test_a_service_that_answers_late_is_waited_for() -> None:
    """A service busy with its first samples (a loaded machine) answers after more than the
    idle timeout: the replay waits for the first answer up to ``first_timeout``, then for the
    rest with the idle timeout; with no answer at all it gives up after ``first_timeout``."""
    from replay.client import FieldClient
    from service.transport import MemoryTransport

    t0 = pd.Timestamp("2017-03-01T06:00:00Z").value
    expected = [("W01", t0 + k * 60 * 10**9) for k in range(3)]
    bus = MemoryTransport()
    with FieldClient(bus, "vfm") as client:
        thread = _answer_later(bus, "W01", [t for _, t in expected], after_s=1.0)
        got = client.wait_for_answers(
            expected, idle_timeout=0.2, final_timeout=30.0, first_timeout=10.0
        )
        thread.join()
        assert got == 3
    with FieldClient(MemoryTransport(), "vfm") as client:
        began = time.monotonic()
        got = client.wait_for_answers(
            expected, idle_timeout=0.2, final_timeout=30.0, first_timeout=1.0
        )
        waited = time.monotonic() - began
        assert got == 0 and 1.0 <= waited < 10.0, waited
