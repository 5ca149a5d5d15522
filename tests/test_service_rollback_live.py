"""The loop through a running service: a right change kept, a wrong one rolled back by its trial.

A two-well field whose chokes wear (``erosion:rate=0.3``, sand erosion: C_D grows 30 % per
year-equivalent of throughput), both wells on ``mm`` learning with ``ol``, the service fitted
on the history before ``SPLIT`` and replayed to ``MID``. Then, as an operator would, over HTTP:

1. the diagnosis of W01 (``POST /wells/W01/diagnosis``) names ``erosion``; its verdict is
   applied (``PUT /wells/W01/model``): the right change;
2. W02 is switched from ``ol`` to ``pbl:182d`` (a batch refit twice a year, e.g. to save CPU):
   a deliberately wrong change on a wearing choke, since between two refits nothing
   re-learns while the choke keeps wearing, and the refit itself fits one C_D to the whole
   worn history. The held-out check sees it (each method learning over the latest fifth
   of the stored history, s54) and asks; confirmed, it is applied and its trial catches it;
3. the replay goes on past the trials (30 days of data and 30 paired measurements).

The trial keeps W01's change (the new model beats its shadow beyond noise) and rolls W02's
back: ``ol`` runs W02 again, with a higher version; the rollback is recorded in the well's
model changes, its versions, the store's ``trials`` table and ``/metrics``. The rolled-back
model kept learning as the shadow: its C_D rose with the wear, and W02's rolling error
after the rollback is below the wrong model's in its trial. The service runs its real engine without a network (the
in-memory transport, as in tests/test_service_trial.py).

Measured on other seeds and wear rates, and in walks through ``vfm serve`` on six-well
fields: docs/guide/trials.md, "A wrong change caught by its trial"
(``benchmarks/bench_trials.py --wrong pbl:182d``).
"""

from __future__ import annotations

import json
import sqlite3
import time
from pathlib import Path
from typing import Any

import httpx
import pandas as pd
import pytest

from replay.replayer import replay_frame
from service.app import running
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(400)

TOKEN = "rollback-live-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SPLIT, MID, END = "2016-06-01", "2016-12-01", "2017-01-20"
WRONG = {"method": "pbl:182d"}


def _ts(text: str) -> pd.Timestamp:
    return pd.Timestamp(text, tz="UTC")


def _diagnosis(http: httpx.Client, well: str, timeout: float = 300.0) -> dict[str, Any]:
    """The well's diagnosis as the page starts it (the default request), waited for."""
    started = http.post(f"/wells/{well}/diagnosis", json={}, headers=AUTH)
    assert started.status_code == 202, started.text
    job = started.json()["job"]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state: dict[str, Any] = http.get(f"/diagnosis/{job}").json()
        if state["state"] in ("done", "failed"):
            assert state["state"] == "done", state
            return dict(state["diagnosis"])
        time.sleep(0.5)
    raise AssertionError(f"the diagnosis of {well} did not finish in {timeout} s")


def _apply_the_diagnosis(http: httpx.Client, well: str) -> None:
    """The diagnosis of ``well`` over HTTP names erosion; its verdict is applied."""
    diag = _diagnosis(http, well)
    verdict = diag["verdict"]
    assert (verdict["kind"], verdict["effect"]) == ("effect", "erosion"), verdict
    right = {"model": diag["model"], "effects": [*diag["base_effects"], verdict["effect"]]}
    applied = http.put(f"/wells/{well}/model", json=right, headers=AUTH)
    assert applied.status_code == 200, applied.text
    assert applied.json()["trial"]["outcome"] == "running"


def _apply_the_wrong_change(http: httpx.Client, well: str) -> int:
    """The wrong change (token needed). The held-out check replays each method over the
    latest stored measurements (s54), so it sees the wrong method and asks first (409,
    both MAPEs and both methods named); confirmed, it is applied and its trial judges it.
    Returns the wrong model's version."""
    assert http.put(f"/wells/{well}/model", json=WRONG).status_code == 401
    asked = http.put(f"/wells/{well}/model", json=WRONG, headers=AUTH)
    assert asked.status_code == 409, asked.text
    assert "mm (pbl:182d) is worse than mm (ol)" in asked.text, asked.text
    wrong = http.put(f"/wells/{well}/model", json={**WRONG, "confirm_worse": True}, headers=AUTH)
    assert wrong.status_code == 200, wrong.text
    change = wrong.json()
    assert change["method"] == "pbl:182d" and change["holdout"]["holdout_rows"] > 20
    assert change["holdout"]["after"] > change["holdout"]["before"]
    assert change["holdout"]["protocol"] == "replayed" and change["holdout"]["confirmed_worse"]
    assert change["trial"]["shadow_model"] == "mm" and change["trial"]["outcome"] == "running"
    return int(change["version_after"])


def _check_kept(kept: dict[str, Any]) -> None:
    """The right change: kept, the new model better than its shadow beyond noise."""
    trial = kept["trial"]
    print("right change's trial:", trial)
    assert (trial["model"], trial["shadow_model"]) == ("mm+erosion", "mm")
    assert trial["outcome"] == "kept" and kept["model"] == "mm+erosion", trial
    assert trial["n"] >= 30 and trial["blocks"] >= 15
    assert trial["mape"] < 0.8 * trial["shadow_mape"], trial
    assert trial["p_value"] > 0.95  # one-sided for "the shadow is better": far from it
    assert kept["parameters"]["erosion.rate"]["value"] > 0.05  # the wear was learned


def _check_rolled_back(before: dict[str, Any], back: dict[str, Any], wrong_version: int) -> None:
    """The wrong change: rolled back by its trial, the previous model running again."""
    trial = back["trial"]
    print("wrong change's trial:", trial)
    assert trial["outcome"] == "rolled_back", trial
    assert (trial["method"], trial["shadow_method"]) == ("pbl:182d", "ol")  # as GET shows it
    assert trial["n"] >= 30 and trial["shadow_mape"] < trial["mape"] and trial["p_value"] < 0.05
    assert "rolled back" in trial["why"]
    # the previous model runs again (it kept learning as the shadow), with a higher version
    assert (back["model"], back["method"]) == ("mm", "ol")
    assert back["version"] > wrong_version
    last = back["model_changes"][-1]
    assert last["kind"] == "trial rollback" and last["method"] == "ol"
    assert last["trial"]["outcome"] == "rolled_back"
    # the versions' notes read once: the trial's reason, not "...; rolled back." twice
    assert last["note"].startswith("rolled back by its trial: The shadow was better"), last
    assert "; rolled back" not in last["note"] and last["note"].endswith("blocks)."), last
    # a change of the method alone is named by its method
    change = back["model_changes"][-2]
    assert change["note"] == "replaced by mm (pbl:182d) over HTTP", change
    assert back["versions"][0]["method"] == "pbl:182d"  # the wrong one kept as a version
    # it learned the wear as the shadow (ol on plain mm raises C_D with the worn choke), and
    # since the rollback it serves the well better than the wrong model did in its trial
    c_d = [w["parameters"]["c_d"]["value"] for w in (before, back)]
    print("W02 c_d at the change and at the end:", c_d, "rolling:", back["rolling_mape"])
    assert c_d[1] > c_d[0], c_d
    rolling = back["rolling_mape"]
    assert rolling["n"] >= 10 and rolling["value"] < trial["mape"], rolling


def _ended_trials(store: Path) -> list[tuple[Any, ...]]:
    """The store's ended trials by well: (well, model, its method, shadow model, its method,
    outcome)."""
    con = sqlite3.connect(store)
    try:
        rows = con.execute("SELECT well, summary, outcome FROM trials ORDER BY well").fetchall()
    finally:
        con.close()
    out = []
    for well, summary, outcome in rows:
        s = json.loads(summary)
        out.append((well, s["model"], s["method"], s["shadow_model"], s["shadow_method"], outcome))
    return out


def test_the_right_change_is_kept_and_a_wrong_one_rolled_back(tmp_path: Path) -> None:
    sim = simulate_field(wells=2, years=1.5, seed=57, hidden=["erosion:rate=0.3"])
    frame = validate_frame(sim.observations).frame
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        tmp_path,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"checkpoint_every": 50},
    )
    assert settings.trial.duration_s == 30 * 86_400 and settings.trial.alpha == 0.05  # defaults
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        t = frame["time"]
        replay_frame(frame[t < _ts(MID)], bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
        before = {w: http.get(f"/wells/{w}").json() for w in ("W01", "W02")}
        _apply_the_diagnosis(http, "W01")
        wrong_version = _apply_the_wrong_change(http, "W02")
        # on past both trials
        replay_frame(
            frame[(t >= _ts(MID)) & (t < _ts(END))], bus=bus, progress=False, idle_timeout=2.0
        )
        after = {w: http.get(f"/wells/{w}").json() for w in ("W01", "W02")}
        metrics = http.get("/metrics").text

    for w in ("W01", "W02"):
        assert (before[w]["model"], before[w]["method"], before[w]["trial"]) == ("mm", "ol", None)
    _check_kept(after["W01"])
    _check_rolled_back(before["W02"], after["W02"], wrong_version)
    assert 'vfm_trials_total{outcome="rolled_back"} 1.0' in metrics
    assert 'vfm_trials_total{outcome="kept"} 1.0' in metrics
    assert _ended_trials(settings.store.path) == [
        ("W01", "mm+erosion", "ol", "mm", "ol", "kept"),
        ("W02", "mm", "pbl:182d", "mm", "ol", "rolled_back"),
    ]
