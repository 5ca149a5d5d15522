"""What the service gives back: predictive intervals (published, stored, served), the
store's history in the observation format (``load_store``, ``vfm export``,
``GET /wells/{well}/history.csv``), and the parameter schema with uncertainty.

One service (``mm`` + ``ol``, fitted on the first months of a simulated well) is fed the
rest over its in-memory transport; a well test is posted over HTTP. The interval columns
are exercised with a learner whose predictions carry an interval (a thin wrapper that adds
one to ``WellLearner.predict``'s answer, as a Bayesian method does) and, when the
``bayes`` method is registered, with the real one.
"""

from __future__ import annotations

import argparse
import io
import json
import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pandas as pd
import pytest

from replay.replayer import replay_frame
from service.app import running
from service.cli import register_export
from service.export import COLUMNS, load_store
from service.http.schemas import WellOut
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.learning import METHODS
from vfm_core.learning.streaming import WellLearner
from vfm_core.observations import load_observations, validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(240)

SPLIT = "2016-05-01"
TOKEN = "export-test-token-0123456789"


@dataclass
class Served:
    folder: Path
    store: Path
    frame: pd.DataFrame
    http: str
    predictions: list[dict[str, Any]]
    history: dict[str, Any]
    csv_text: str
    csv_plain: str
    well_test: dict[str, Any]


def _with_interval(original: Any) -> Any:
    """WellLearner.predict with a 10 % log-normal interval added, as a Bayesian method gives."""

    def predict(self: WellLearner, inputs: Any, when: Any = None) -> dict[str, float | None]:
        out = original(self, inputs, when)
        q = out.get("q_total")
        if q is not None:
            out.update(q_total_std=0.1 * q, q_total_p05=q * 0.85, q_total_p95=q * 1.18)
        return out

    return predict


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    folder = tmp_path_factory.mktemp("export")
    frame = validate_frame(simulate_field(wells=1, years=1, seed=2).observations).frame
    frame = frame[frame["time"] < pd.Timestamp("2016-08-01", tz="UTC")].reset_index(drop=True)
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
    )
    bus = MemoryTransport(settings.prefix)
    predictions: list[dict[str, Any]] = []
    with pytest.MonkeyPatch.context() as mp:  # only while this service runs
        mp.setattr(WellLearner, "predict", _with_interval(WellLearner.predict))
        with running(settings, bus) as svc:
            bus.subscribe("vfm/*/prediction", lambda k, p: predictions.append(json.loads(p)))
            replay_frame(frame, bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
            last = frame[frame["q_total"].notna()].iloc[-1]  # an MPFM reading's time
            with httpx.Client(base_url=svc.http_url, timeout=30) as http:
                posted = http.post(
                    "/wells/W01/well-tests",
                    json={"time": last["time"].isoformat(), "q_total": float(last["q_total"])},
                    headers={"Authorization": f"Bearer {TOKEN}"},
                )
                history = http.get("/wells/W01/history", params={"start": SPLIT}).json()
                csv_text = http.get("/wells/W01/history.csv").text
                csv_plain = http.get(
                    "/wells/W01/history.csv", params={"comment": "false", "start": SPLIT}
                ).text
    yield Served(
        folder,
        settings.store.path,
        frame,
        svc.http_url,
        predictions,
        history,
        csv_text,
        csv_plain,
        posted.json() | {"status_code": posted.status_code},
    )


def test_intervals_are_published_stored_and_served(served: Served) -> None:
    assert served.predictions
    for p in served.predictions:
        q = p["q_total"]
        assert p["q_total_std"] == pytest.approx(0.1 * q)
        assert p["q_total_p05"] < q < p["q_total_p95"]
    preds = served.history["predictions"]
    assert preds and all(p["q_total_std"] == pytest.approx(0.1 * p["q_total"]) for p in preds)
    con = sqlite3.connect(served.store)
    n_null, n_all = con.execute(
        "SELECT SUM(q_total_p95 IS NULL), COUNT(*) FROM samples WHERE q_total IS NOT NULL"
    ).fetchone()
    con.close()
    assert n_all > 0 and n_null == 0


def test_a_method_without_intervals_stores_nulls(tmp_path: Path) -> None:
    frame = validate_frame(simulate_field(wells=1, years=1, seed=2).observations).frame
    frame = frame[frame["time"] < pd.Timestamp("2016-06-01", tz="UTC")]
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        tmp_path,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
    )
    bus = MemoryTransport(settings.prefix)
    got: list[dict[str, Any]] = []
    with running(settings, bus) as svc:
        bus.subscribe("vfm/*/prediction", lambda k, p: got.append(json.loads(p)))
        replay_frame(frame, bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
        history = httpx.get(f"{svc.http_url}/wells/W01/history", timeout=30).json()
    assert got and all(p["q_total_std"] is None and p["q_total_p05"] is None for p in got)
    assert all(p["q_total_p95"] is None for p in history["predictions"])


@pytest.mark.skipif("bayes" not in METHODS, reason="the bayes method is not registered yet")
def test_bayes_gives_real_intervals(tmp_path: Path) -> None:
    frame = validate_frame(simulate_field(wells=1, years=1, seed=2).observations).frame
    frame = frame[frame["time"] < pd.Timestamp("2016-07-01", tz="UTC")]
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        tmp_path,
        model={"name": "mm", "method": "bayes", "history": str(data), "history_until": SPLIT},
    )
    bus = MemoryTransport(settings.prefix)
    got: list[dict[str, Any]] = []
    with running(settings, bus) as svc:
        bus.subscribe("vfm/*/prediction", lambda k, p: got.append(json.loads(p)))
        replay_frame(frame, bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
        state = httpx.get(f"{svc.http_url}/wells/W01", timeout=30).json()
    assert got and all(p["q_total_p05"] < p["q_total"] < p["q_total_p95"] for p in got)
    assert any(p.get("std") is not None for p in state["parameters"].values())


def test_the_parameter_schema_takes_uncertainty_before_and_after() -> None:
    base: dict[str, Any] = {
        "well": "W01",
        "model": "mm",
        "method": "bayes",
        "ready": True,
        "version": 3,
        "n_updates": 3,
        "last_update": None,
        "rolling_mape": {"value": None, "n": 0, "window": 50},
        "measurements_remembered": 10,
        "model_changes": [],
        "drift": {},
        "samples": 0,
        "measurements": 0,
        "last_sample_time": None,
        "pending_measurements": 0,
    }
    plain = WellOut.model_validate({**base, "parameters": {"c_d": {"value": 0.8, "unit": "-"}}})
    assert plain.parameters["c_d"].std is None
    full = WellOut.model_validate(
        {
            **base,
            "parameters": {
                "c_d": {
                    "value": 0.8,
                    "unit": "-",
                    "std": 0.02,
                    "low": 0.3,
                    "high": 1.2,
                    "at_bound": False,
                }
            },
        }
    )
    assert full.parameters["c_d"].std == 0.02 and full.parameters["c_d"].at_bound is False


def test_load_store_gives_the_observation_format(served: Served) -> None:
    frame = load_store(str(served.store))
    assert list(frame.columns) == list(COLUMNS)
    assert str(frame["time"].dtype) == "datetime64[ns, UTC]"
    checked = validate_frame(frame)  # the observation format's own checks
    assert len(checked.frame) == len(frame)
    con = sqlite3.connect(served.store)
    n_samples = con.execute("SELECT COUNT(*) FROM samples").fetchone()[0]
    learned = con.execute(
        "SELECT time_ns, sample_time_ns, q_total, source FROM measurements WHERE status = 'learned'"
    ).fetchall()
    con.close()
    apart = [r for r in learned if r[0] != r[1]]
    # a sample whose time an MPFM reading and a well test share has a row per source
    shared = len([r for r in learned if r[0] == r[1]]) - len(
        {r[0] for r in learned if r[0] == r[1]}
    )
    assert served.well_test["status_code"] == 200 and shared == 1
    assert len(frame) == n_samples + len(apart) + shared
    measured = frame[frame["q_total"].notna()]
    assert len(measured) == len(learned)
    assert set(measured["source"]) <= {"mpfm", "well_test"}
    # a learned measurement sits on its paired sample's row when their times coincide
    same = [r for r in learned if r[0] == r[1]]
    assert same
    t_ns, _, q, source = same[0]
    row = frame[frame["time"] == pd.Timestamp(t_ns, unit="ns", tz="UTC")]
    assert (row["q_total"] == q).any() and (row["source"] == source).any()
    assert frame["predicted"].notna().sum() > 0.9 * n_samples
    one = load_store(str(served.store), "W01")
    assert len(one) == len(frame)
    with pytest.raises(Exception, match="no well 'NOPE'"):
        load_store(str(served.store), "NOPE")


def test_history_csv_matches_the_export(served: Served) -> None:
    head = served.csv_text.splitlines()[0]
    assert head.startswith("# ") and "bar absolute" in head and "Sm3/h" in head
    csv = pd.read_csv(io.StringIO(served.csv_text), comment="#")
    assert list(csv.columns) == list(COLUMNS)
    exported = load_store(str(served.store), "W01")
    assert len(csv) == len(exported)
    assert (csv["q_total"].notna()).sum() == exported["q_total"].notna().sum()
    # without the comment line, the observation reader takes the file as it is
    path = served.folder / "from-http.csv"
    path.write_text(served.csv_plain, encoding="utf-8")
    loaded = load_observations(path)
    assert len(loaded.frame) > 0
    assert loaded.frame["time"].min() >= pd.Timestamp(SPLIT, tz="UTC")


def test_vfm_export_writes_parquet_and_csv(served: Served, tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    register_export(sub)
    for name in ("store.parquet", "store.csv"):
        out = tmp_path / name
        args = parser.parse_args(["export", "--store", str(served.store), "--out", str(out)])
        assert args.handler(args) == 0
        loaded = load_observations(out)
        assert len(loaded.frame) == len(load_store(str(served.store)))
    bad = parser.parse_args(["export", "--store", str(served.store), "--out", "x.txt"])
    with pytest.raises(Exception, match=r"\.parquet or \.csv"):
        bad.handler(bad)
    missing = parser.parse_args(
        ["export", "--store", str(tmp_path / "no.sqlite"), "--out", "x.csv"]
    )
    with pytest.raises(Exception, match="does not exist"):
        missing.handler(missing)


def test_the_export_opens_the_store_read_only(served: Served) -> None:
    """Reading never writes: the file is unchanged and a write through the same kind of
    connection is refused."""
    from service.export import connect_read_only

    before = served.store.read_bytes()
    con = connect_read_only(served.store)
    try:
        with pytest.raises(sqlite3.OperationalError, match="readonly"):
            con.execute("DELETE FROM samples")
    finally:
        con.close()
    load_store(str(served.store))
    assert served.store.read_bytes() == before
