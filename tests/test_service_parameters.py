"""The parameter history (``GET /wells/{well}/parameters``, store table ``parameter_history``)
and the alarm when a well's MPFM disagrees with its well tests.

One service (``mm`` + ``bayes``, fitted on the first quarter of a simulated two-well field)
runs on its in-memory transport; the rest of the year is replayed into it. W02 is in the
history; W01 starts in July (a new well). The MPFM readings of W01 are multiplied by 1.2 in
the frame (a meter reading 20 % high); W02's are left as simulated.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pandas as pd
import pytest

from replay.replayer import replay_frame
from service.app import running
from service.store import InsertParameters, PruneParameters, Store
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-04-01"
MID = "2016-06-01"
TOKEN = "parameters-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
BIAS = 1.2
RATES = ["q_total", "q_gas", "q_oil", "q_water"]


@dataclass
class Live:
    http: httpx.Client
    bus: MemoryTransport
    frame: pd.DataFrame


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    folder = tmp_path_factory.mktemp("parameters")
    sim = simulate_field(wells=2, years=1.0, seed=4)
    frame = validate_frame(sim.observations).frame
    biased = (frame["well"] == "W01") & (frame["source"] == "mpfm")
    frame.loc[biased, RATES] = frame.loc[biased, RATES] * BIAS
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "bayes", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"parameters_every": 5},
    )
    bus = MemoryTransport(settings.prefix)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=60) as http:
        yield Live(http, bus, frame)


def _replay(live: Live, start: str, end: str | None = None) -> None:
    rows = live.frame[live.frame["time"] >= pd.Timestamp(start, tz="UTC")]
    if end is not None:
        rows = rows[rows["time"] < pd.Timestamp(end, tz="UTC")]
    replay_frame(rows, bus=live.bus, start=start, progress=False, idle_timeout=2.0)


def _parameters(live: Live, well: str = "W02", **params: Any) -> dict[str, Any]:
    r = live.http.get(f"/wells/{well}/parameters", params=params)
    assert r.status_code == 200, r.text
    return r.json()


def test_the_parameter_history_grows_as_a_replay_streams(live: Live) -> None:
    fitted = _parameters(live)
    assert fitted["rows"] >= 1  # the fit on the history is the first row, at the split
    _replay(live, SPLIT, MID)
    after = _parameters(live)
    assert after["rows"] > fitted["rows"] + 5, (fitted["rows"], after["rows"])
    c_d = after["parameters"]["c_d"]
    times = pd.to_datetime(c_d["time"])
    assert times.is_monotonic_increasing and times[-1] < pd.Timestamp(MID, tz="UTC")
    assert times[0] <= pd.Timestamp(SPLIT, tz="UTC") < times[-1]
    # bayes keeps a posterior: every row has a positive sd; the bounds come with the series
    assert all(s is not None and s > 0 for s in c_d["std"]), c_d["std"]
    assert c_d["low"] is not None and c_d["high"] is not None and c_d["unit"] == "-"
    assert all(c_d["low"] <= v <= c_d["high"] for v in c_d["value"])
    assert len(set(c_d["value"])) > 1  # it is learned, not a constant
    assert c_d["version"] == sorted(c_d["version"])
    assert after["model_changes"] == [] and after["truncated"] is False

    # limit returns the latest rows, oldest first, and says more were there
    two = _parameters(live, limit=2)
    assert two["rows"] == 2 and two["truncated"] is True
    assert two["parameters"]["c_d"]["time"] == c_d["time"][-2:]
    # since / until select a window
    window = _parameters(live, since=c_d["time"][1], until=c_d["time"][3])
    assert window["parameters"]["c_d"]["time"] == c_d["time"][1:3]


@pytest.mark.parametrize(
    ("params", "words"),
    [
        ({"since": "yesterday"}, "ISO 8601"),
        ({"until": "3000-01-01T00:00:00Z"}, "until"),
        ({"since": "2016-05-01T00:00:00Z", "until": "2016-04-01T00:00:00Z"}, "must be after"),
        ({"limit": 0}, "limit"),
        ({"limit": 1_000_000}, "limit"),
    ],
)
def test_bad_parameter_queries_get_422_with_a_sentence(
    live: Live, params: dict[str, Any], words: str
) -> None:
    r = live.http.get("/wells/W02/parameters", params=params)
    assert r.status_code == 422, r.text
    assert words in r.json()["detail"], r.json()


def test_an_unknown_well_has_no_parameters(live: Live) -> None:
    r = live.http.get("/wells/W99/parameters")
    assert r.status_code == 404 and "W99" in r.json()["detail"]


def test_the_mpfm_reading_above_the_well_tests_raises_an_alarm_on_that_well_only(
    live: Live,
) -> None:
    _replay(live, MID)
    views = {v["well"]: v for v in live.http.get("/wells").json()}
    biased = views["W01"]["mpfm_check"]
    assert biased is not None and biased["agrees"] is False, biased
    assert biased["alarm"].startswith("MPFM reads") and "above the well test of" in biased["alarm"]
    assert 0.12 < biased["relative_difference"] < 0.28, biased
    fair = views["W02"]["mpfm_check"]
    assert fair is not None and fair["agrees"] is True and fair["alarm"] is None, fair
    assert abs(fair["relative_difference"]) < 0.1
    # the well view says the same
    assert live.http.get("/wells/W01").json()["mpfm_check"] == biased

    # a later well test that agrees with the meter clears the alarm (posted at the time of
    # the last MPFM reading, whose sample is stored)
    w01 = live.frame[(live.frame["well"] == "W01") & (live.frame["source"] == "mpfm")]
    last = w01["time"].iloc[-1]
    near = w01[(w01["time"] - last).abs() <= pd.Timedelta("24h")]
    posted = live.http.post(
        "/wells/W01/well-tests",
        json={"time": last.isoformat(), "q_total": float(near["q_total"].median())},
        headers=AUTH,
    )
    assert posted.status_code == 200, posted.text
    cleared = live.http.get("/wells/W01").json()["mpfm_check"]
    assert cleared["agrees"] is True and cleared["alarm"] is None, cleared
    assert cleared["well_test_time"].startswith(last.isoformat()[:19])


def test_parameter_rows_are_pruned_to_the_latest(tmp_path: Path) -> None:
    store = Store(tmp_path / "s.sqlite")
    try:
        for i in range(15):
            store.write(
                [
                    InsertParameters("W01", 1_000 + i, i, "mm", '{"c_d": {"value": 0.8}}'),
                    PruneParameters("W01", keep=10),
                ]
            )
        store.write([InsertParameters("W02", 5, 1, "mm", "{}")])
        rows, more = store.parameter_history("W01", 0, 2**62, 100)
        assert [r.version for r in rows] == list(range(5, 15)) and more is False
        assert store.counts()["parameter_history"] == 11  # the other well's row untouched
    finally:
        store.close()
