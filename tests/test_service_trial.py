"""A model change proves itself against the model it replaced (service.engine.trial).

Unit tests of the rule (the one-sided t-test on daily block means of paired differences of
absolute percentage errors), then the loop through a running service on a simulated eroding
field: ``mm`` + ``erosion`` applied to an ``mm`` well beats its shadow and is kept; a
deliberately wrong change (dropping the effect again, which the held-out check calls worse,
so it needs ``confirm_worse``) is rolled back automatically; a one-click rollback brings an
earlier version back; a trial survives a restart.

The service runs its real engine without a network (the in-memory transport, as in
tests/test_service_model_change.py).
"""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest

from replay.replayer import replay_frame
from service.app import running
from service.config import TrialSettings
from service.engine.trial import Trial, block_test, decide
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.learning.streaming import WellLearner
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(400)

TOKEN = "trial-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SPLIT, MID, END = "2016-06-01", "2016-12-01", "2017-02-15"


# -- the rule ----------------------------------------------------------------------------------
def _blocks(rng: np.random.Generator, days: int, per_day: int, shift: float) -> list[Any]:
    """Paired APEs (fractions) with a day-level error common to a day's measurements of
    both models' differences (autocorrelated meter and operating point) and ``shift`` added
    to the new model's error."""
    out = []
    for _ in range(days):
        day = rng.normal(0.0, 0.02)  # the difference's day-level part
        base = np.abs(rng.normal(0.04, 0.01, per_day))
        diff = day + rng.normal(0.0, 0.005, per_day) + shift
        new = np.clip(base + diff, 0.0, None)
        out.append((per_day, float(new.sum()), float(base.sum())))
    return out


def test_a_shadow_clearly_better_is_a_rollback() -> None:
    rng = np.random.default_rng(11)
    verdict = decide("block_t", 0.05, _blocks(rng, 30, 12, shift=0.03))
    assert verdict["outcome"] == "rolled_back", verdict
    assert verdict["p_value"] < 0.01 and verdict["mean_diff"] > 1.0
    assert "rolled back" in verdict["why"]


def test_a_better_new_model_is_kept() -> None:
    rng = np.random.default_rng(12)
    verdict = decide("block_t", 0.05, _blocks(rng, 30, 12, shift=-0.03))
    assert verdict["outcome"] == "kept" and verdict["p_value"] > 0.99, verdict


def test_the_rule_holds_its_level_against_day_correlated_errors() -> None:
    """Under no difference the rule rolls back at about its alpha; a test on the single
    measurements, blind to the day-level correlation, would roll back far more often."""
    rng = np.random.default_rng(13)
    trials, rolled, naive = 600, 0, 0
    from scipy import stats

    for _ in range(trials):
        blocks = _blocks(rng, 30, 12, shift=0.0)
        rolled += decide("block_t", 0.05, blocks)["outcome"] == "rolled_back"
        # the same data, per measurement as if independent: day means repeated per_day times
        d = np.repeat([(sn - ss) / n for n, sn, ss in blocks], 12)
        d = d + rng.normal(0.0, 0.005, d.size)
        t = d.mean() / (d.std(ddof=1) / np.sqrt(d.size))
        naive += stats.t.sf(t, d.size - 1) < 0.05
    rate = rolled / trials
    assert 0.02 <= rate <= 0.085, rate  # binomial 95 % band around 0.05 for 600 trials
    assert naive / trials > 2 * rate, (naive / trials, rate)


def test_too_few_blocks_or_the_keep_rule_never_roll_back() -> None:
    one = [(20, 2.0, 0.5)]
    assert block_test(one)["p_value"] is None
    verdict = decide("block_t", 0.05, one)
    assert verdict["outcome"] == "kept" and "too few" in verdict["why"]
    rng = np.random.default_rng(14)
    worse = _blocks(rng, 30, 12, shift=0.05)
    assert decide("block_t", 0.05, worse)["outcome"] == "rolled_back"
    assert decide("keep", 0.05, worse)["outcome"] == "kept"
    assert block_test([])["blocks"] == 0


def test_a_trial_round_trips_through_its_state() -> None:
    shadow = WellLearner("W01", "mm", "ol")
    trial = Trial(
        well="W01",
        since_ns=10**18,
        model="mm+erosion",
        shadow_model="mm",
        version=8,
        shadow_version=7,
        shadow=shadow,
        settings=TrialSettings(duration_s=86_400 * 10, min_pairs=5),
    )
    trial.blocks = {0: [3, 0.3, 0.6], 1: [2, 0.1, 0.3]}
    trial.n, trial.sum_new, trial.sum_shadow = 5, 0.4, 0.9
    data = json.loads(json.dumps(trial.state()))
    back, problem = Trial.restore(data)
    assert problem is None and back.shadow is not None
    assert back.view() == trial.view()
    assert back.view()["mape"] == pytest.approx(8.0) and back.view()["shadow_mape"] == 18.0
    data["shadow"] = None
    lost, problem = Trial.restore(data)
    assert lost.shadow is None and "no shadow" in str(problem)


# -- through the service -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> tuple[pd.DataFrame, Path]:
    folder = tmp_path_factory.mktemp("trial-field")
    sim = simulate_field(wells=1, years=1.5, seed=21, hidden=["erosion:rate=0.4"])
    frame = validate_frame(sim.observations).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    return frame, data


def _settings(folder: Path, data: Path, **trial: Any) -> Any:
    return loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"checkpoint_every": 20},
        trial={"duration_s": 30 * 86_400.0, **trial},
    )


def _part(frame: pd.DataFrame, start: str | None, end: str | None) -> pd.DataFrame:
    t = frame["time"]
    keep = np.ones(len(frame), dtype=bool)
    if start is not None:
        keep &= (t >= pd.Timestamp(start, tz="UTC")).to_numpy()
    if end is not None:
        keep &= (t < pd.Timestamp(end, tz="UTC")).to_numpy()
    return frame[keep]


def test_the_loop_keeps_a_good_change_and_rolls_back_a_wrong_one(
    tmp_path: Path, field: tuple[pd.DataFrame, Path]
) -> None:
    frame, data = field
    settings = _settings(tmp_path, data)
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        replay_frame(_part(frame, None, MID), bus=bus, start=SPLIT, progress=False, idle_timeout=2)
        assert http.get("/wells/W01").json()["trial"] is None

        # the effect the field hides: applied, on trial against plain mm, kept
        good = http.put("/wells/W01/model", json={"effects": ["erosion"]}, headers=AUTH)
        assert good.status_code == 200, good.text
        started = good.json()["trial"]
        assert started["outcome"] == "running" and started["n"] == 0
        assert (started["model"], started["shadow_model"]) == ("mm+erosion", "mm")
        replay_frame(_part(frame, MID, "2017-01-15"), bus=bus, progress=False, idle_timeout=2)
        kept = http.get("/wells/W01").json()
        trial = kept["trial"]
        assert kept["model"] == "mm+erosion" and trial["outcome"] == "kept", trial
        assert trial["n"] >= 30 and trial["blocks"] >= 20
        # the shadow learned along (its error stays finite and near the live one's scale),
        # and the effect beat it on the same measurements
        assert trial["mape"] < 0.75 * trial["shadow_mape"], trial
        assert trial["p_value"] > 0.5
        assert [v["model"] for v in kept["versions"]] == ["mm"]

        # a deliberately wrong change: drop the effect again. The held-out check says worse:
        # refused with both MAPEs, applied only when confirmed
        wrong = {"effects": []}
        refused = http.put("/wells/W01/model", json=wrong, headers=AUTH)
        assert refused.status_code == 409, refused.text
        detail = refused.json()["detail"]
        assert "worse" in detail and "confirm_worse" in detail and detail.count(" %") >= 2
        assert http.get("/wells/W01").json()["model"] == "mm+erosion"
        confirmed = http.put(
            "/wells/W01/model", json={**wrong, "confirm_worse": True}, headers=AUTH
        )
        assert confirmed.status_code == 200, confirmed.text
        assert confirmed.json()["holdout"]["after"] > confirmed.json()["holdout"]["before"]
        assert confirmed.json()["holdout"]["confirmed_worse"] is True  # the reply says so
        version_wrong = confirmed.json()["version_after"]
        observer = svc.engine.observer
        observer.client_capacity = 1_000_000  # every event of the replay kept for the check
        live = observer.subscribe("W01")
        replay_frame(
            _part(frame, "2017-01-15", "2017-03-15"), bus=bus, progress=False, idle_timeout=2
        )
        back = http.get("/wells/W01").json()
        metrics = http.get("/metrics").text
        assert http.get("/wells/W01/model/versions").json() == back["versions"]
        events, dropped = live.take()
        observer.unsubscribe(live)

        # one-click rollback: token needed, unknown version refused, then back to plain mm
        assert http.post("/wells/W01/model/rollback", json={"version": 1}).status_code == 401
        missing = http.post("/wells/W01/model/rollback", json={"version": 1}, headers=AUTH)
        assert missing.status_code == 422 and "not kept" in missing.json()["detail"]
        first = back["versions"][-1]
        assert first["model"] == "mm"
        manual = http.post(
            "/wells/W01/model/rollback", json={"version": first["version"]}, headers=AUTH
        )
        assert manual.status_code == 200, manual.text
        after_manual = http.get("/wells/W01").json()
        replay_frame(_part(frame, "2017-03-15", None), bus=bus, progress=False, idle_timeout=2)
        final = http.get("/wells/W01").json()

    trial = back["trial"]
    print("wrong change's trial:", trial)
    assert trial["outcome"] == "rolled_back", trial
    assert (trial["model"], trial["shadow_model"]) == ("mm", "mm+erosion")
    assert trial["shadow_mape"] < trial["mape"] and trial["p_value"] < 0.05
    # the shadow (which kept learning) is live again, with a higher version, recorded
    assert back["model"] == "mm+erosion" and back["version"] > version_wrong
    last = back["model_changes"][-1]
    assert last["kind"] == "trial rollback" and last["model_after"] == "mm+erosion"
    assert back["parameters"]["erosion.rate"]["value"] > 0.05
    assert [v["model"] for v in back["versions"]] == ["mm", "mm+erosion", "mm"]
    assert 'vfm_trials_total{outcome="rolled_back"} 1.0' in metrics
    # live: the trial's end, and the rollback as a model event (the page's chart marker)
    assert dropped == 0
    ended = [e for e in events if e["type"] == "trial"]
    assert [(e["outcome"], e["model"]) for e in ended] == [("rolled_back", "mm")], ended
    models = [e for e in events if e["type"] == "model"]
    assert [m["model_after"] for m in models] == ["mm+erosion"], models
    assert 'vfm_trials_total{outcome="kept"} 1.0' in metrics
    assert 'role="shadow"' in metrics and 'role="model"' in metrics
    # the manual rollback: plain mm again, recorded, no trial of its own
    change = manual.json()
    assert change["kind"] == "rollback" and change["model_after"] == "mm"
    assert change["rolled_back_to"] == first["version"] and change["relearned"] > 50
    assert after_manual["model"] == "mm" and after_manual["version"] > back["version"]
    assert final["model"] == "mm" and final["trial"]["outcome"] == "rolled_back"
    # the store records the ended trials
    con = sqlite3.connect(settings.store.path)
    outcomes = [r[0] for r in con.execute("SELECT outcome FROM trials ORDER BY id")]
    con.close()
    assert outcomes == ["kept", "rolled_back"]


def _settled(store: Path, measurements: int, timeout: float = 30.0) -> None:
    """Wait until the store holds every measurement sent, none of them still pending."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        con = sqlite3.connect(store)
        try:
            done = con.execute(
                "SELECT COUNT(*) FROM measurements WHERE status != 'pending'"
            ).fetchone()[0]
        finally:
            con.close()
        if done >= measurements:
            return
        time.sleep(0.1)
    raise AssertionError(f"{done} of {measurements} measurements settled in {timeout} s")


def test_a_trial_survives_a_restart(tmp_path: Path, field: tuple[pd.DataFrame, Path]) -> None:
    frame, data = field
    settings = _settings(tmp_path, data)
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        replay_frame(_part(frame, None, MID), bus=bus, start=SPLIT, progress=False, idle_timeout=2)
        assert http.put("/wells/W01/model", json={"effects": ["erosion"]}, headers=AUTH).is_success
        replay_frame(_part(frame, MID, "2016-12-15"), bus=bus, progress=False, idle_timeout=2)
        # the replay waits for the predictions; the last measurements may still be queued
        sent = _part(frame, SPLIT, "2016-12-15")["q_total"].notna().sum()
        _settled(settings.store.path, int(sent))
        before = http.get("/wells/W01").json()["trial"]
    assert before["outcome"] == "running" and before["n"] > 5

    settings = _settings(tmp_path, data)
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        again = http.get("/wells/W01").json()["trial"]
        replay_frame(
            _part(frame, "2016-12-15", "2017-01-15"), bus=bus, progress=False, idle_timeout=2
        )
        ended = http.get("/wells/W01").json()["trial"]
    # restored with its shadow: the same pairs and errors, and it goes on to its end
    assert again["outcome"] == "running" and again["n"] == before["n"]
    assert again["mape"] == pytest.approx(before["mape"], rel=1e-9)
    assert again["shadow_mape"] == pytest.approx(before["shadow_mape"], rel=1e-6)
    assert ended["outcome"] == "kept" and ended["n"] > again["n"]


def test_a_trial_without_its_shadow_ends_interrupted(
    tmp_path: Path, field: tuple[pd.DataFrame, Path]
) -> None:
    frame, data = field
    settings = _settings(tmp_path, data)
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        replay_frame(_part(frame, None, MID), bus=bus, start=SPLIT, progress=False, idle_timeout=2)
        assert http.put("/wells/W01/model", json={"effects": ["erosion"]}, headers=AUTH).is_success
        replay_frame(_part(frame, MID, "2016-12-10"), bus=bus, progress=False, idle_timeout=2)
    # the shadow's checkpoint lost (e.g. a store written by an older service)
    con = sqlite3.connect(settings.store.path)
    rows = con.execute("SELECT id, extra FROM checkpoints WHERE well = 'W01'").fetchall()
    for rid, extra in rows:
        data_ = json.loads(extra)
        if data_.get("trial"):
            data_["trial"]["shadow"] = None
        con.execute("UPDATE checkpoints SET extra = ? WHERE id = ?", (json.dumps(data_), rid))
    con.commit()
    con.close()
    settings = _settings(tmp_path, data)
    with (
        running(settings, MemoryTransport(settings.prefix, 1000)) as svc,
        httpx.Client(base_url=svc.http_url) as http,
    ):
        view = http.get("/wells/W01").json()
    assert view["model"] == "mm+erosion"
    assert view["trial"]["outcome"] == "interrupted" and "restart" in view["trial"]["why"]


def test_the_trial_settings_are_checked() -> None:
    from service.config import load_settings
    from vfm_core.errors import ConfigError

    settings = load_settings(trial={"alpha": 0.1, "rule": "keep", "duration_s": 7 * 86_400.0})
    assert (settings.trial.alpha, settings.trial.rule) == (0.1, "keep")
    assert settings.trial.min_pairs == 30 and settings.trial.block_s == 86_400.0
    for bad in ({"alpha": 1.5}, {"rule": "sometimes"}, {"duration_s": 0}, {"keep_versions": 0}):
        with pytest.raises((ConfigError, ValueError)):
            load_settings(trial=bad)
