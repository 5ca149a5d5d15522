"""A running service swaps a well's model for one with an effect, over HTTP.

The field hides strong choke wear; the service runs plain ``mm`` fitted once on the
first months (``pbl:3650d``: no retrain later, so a missing effect shows as a growing
error). Part-way through the replay an operator replaces the model by ``mm+erosion``
with one token-protected call, while the replay goes on: the new model is fitted on the
well's stored history, swapped in with a higher version, nothing sent is lost (what
streams in during the fit is taught to the new model too), the rolling error over the
rest of the replay falls, and the choice survives a restart.

The engine's code path is the real one, without a network: the replay sends through the
service's in-memory transport (``MemoryTransport``), which hands every input to the same
receiver path as Zenoh; the Zenoh path itself is tested end to end elsewhere.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest

from replay.replayer import ReplayResult, replay_frame
from service.app import running
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(300)

SPLIT = "2016-06-01"
MID = "2016-12-01"
LATER = "2017-02-01"
TOKEN = "model-change-token-0123456789"


def _settings(folder: Any, data: Any) -> Any:
    return loopback_settings(
        folder,
        model={"name": "mm", "method": "pbl:3650d", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"checkpoint_every": 50},
    )


def _memory(settings: Any) -> MemoryTransport:
    return MemoryTransport(settings.prefix, settings.queues.receive_capacity)


def test_model_change_over_http(tmp_path: Any) -> None:
    field = simulate_field(wells=1, years=1.5, seed=4, hidden=["erosion:rate=0.4"])
    frame = validate_frame(field.observations).frame
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    mid, later = pd.Timestamp(MID, tz="UTC"), pd.Timestamp(LATER, tz="UTC")
    first = frame[frame["time"] < mid]
    second = frame[(frame["time"] >= mid) & (frame["time"] < later)]
    third = frame[frame["time"] >= later]
    auth = {"Authorization": f"Bearer {TOKEN}"}
    body = {"effects": ["erosion"]}

    settings = _settings(tmp_path, data)
    bus = _memory(settings)
    with (
        running(settings, bus) as svc,
        httpx.Client(base_url=svc.http_url, timeout=300) as http,
    ):
        replay_frame(first, bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
        before = http.get("/wells/W01").json()
        assert before["model"] == "mm"

        # refused without the token, for a typo, and for an unknown well
        assert http.put("/wells/W01/model", json=body).status_code == 401
        bad = http.put("/wells/W01/model", json={"effects": ["erosoin"]}, headers=auth)
        assert bad.status_code == 422 and "Unknown effect 'erosoin'" in bad.json()["detail"]
        assert http.put("/wells/W99/model", json=body, headers=auth).status_code == 404

        # the change, while the second part streams in; the third comes after it
        done: list[ReplayResult] = []
        # two months at 2.5e6 x real time: about 2 s, while the new model is being fitted
        feeder = threading.Thread(
            target=lambda: done.append(
                replay_frame(second, bus=bus, progress=False, idle_timeout=3.0, speed=2.5e6)
            )
        )
        feeder.start()
        time.sleep(0.3)
        reply = http.put("/wells/W01/model", json=body, headers=auth)
        feeder.join(240)
        assert reply.status_code == 200, reply.text
        change = reply.json()
        done.append(replay_frame(third, bus=bus, progress=False, idle_timeout=2.0))
        after = http.get("/wells/W01").json()
        health = http.get("/health").json()

    print("change:", change, "rolling after:", after["rolling_mape"])
    assert change["model_before"] == "mm" and change["model_after"] == "mm+erosion"
    assert change["version_after"] > change["version_before"] >= before["version"]
    # measurements arrived during the fit: the old model learned them and so did the new one
    assert change["caught_up"] > 0, change
    # the effect helps on the held-out latest fifth of the stored history
    hold = change["holdout"]
    assert hold["holdout_rows"] > 50 and hold["after"] < 0.7 * hold["before"], hold
    # the state shows the new model, its wear rate (unit given) and its own rolling error
    assert after["model"] == "mm+erosion" and after["version"] >= change["version_after"]
    assert after["parameters"]["erosion.rate"]["value"] > 0.05
    assert after["parameters"]["erosion.rate"]["unit"] == "1/yr-eq"
    assert [c["model_after"] for c in after["model_changes"]] == ["mm+erosion"]
    assert after["rolling_mape"]["n"] > 0
    assert after["rolling_mape"]["value"] < 0.7 * change["rolling_mape_before"], (after, change)
    # nothing lost: every sample answered, every measurement learned and remembered
    assert [r.missing for r in done] == [0, 0]
    assert health["rejected_total"] == 0 and health["overflow"] == 0
    learned = int((frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")).sum())
    measured = frame["q_total"].notna().to_numpy()
    history = int((measured & (frame["time"] < pd.Timestamp(SPLIT, tz="UTC")).to_numpy()).sum())
    learned = int((measured & (frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")).to_numpy()).sum())
    assert health["accepted"]["measurements"] == learned
    assert after["measurements_remembered"] == history + learned

    # a restart keeps the model chosen over HTTP (the config still says mm), with its state
    # and the rolling error of the new model only
    settings = _settings(tmp_path, data)
    with (
        running(settings, _memory(settings)) as svc,
        httpx.Client(base_url=svc.http_url) as http,
    ):
        again = http.get("/wells/W01").json()
    assert again["model"] == "mm+erosion" and again["version"] == after["version"]
    assert np.isclose(
        again["parameters"]["erosion.rate"]["value"], after["parameters"]["erosion.rate"]["value"]
    )
    assert again["rolling_mape"]["n"] == after["rolling_mape"]["n"]
    assert np.isclose(again["rolling_mape"]["value"], after["rolling_mape"]["value"])
    # a later edit of the config wins over the HTTP choice
    edited = _settings(tmp_path, data)
    edited.model.effects = ["erosion", "real_gas"]
    with running(edited, _memory(edited)) as svc, httpx.Client(base_url=svc.http_url) as http:
        configured = http.get("/wells/W01").json()
    assert configured["model"] == "mm+erosion+real_gas"


def test_effects_from_modules_need_to_be_allowed(
    tmp_path: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples"))
    field = simulate_field(wells=1, years=0.5, seed=4)
    data = tmp_path / "field.parquet"
    validate_frame(field.observations).frame.to_parquet(data)
    auth = {"Authorization": f"Bearer {TOKEN}"}
    body = {"effects": ["my_effects:TemperatureScale"]}
    settings = _settings(tmp_path, data)
    with (
        running(settings, _memory(settings)) as svc,
        httpx.Client(base_url=svc.http_url) as http,
    ):
        refused = http.put("/wells/W01/model", json=body, headers=auth)
    assert refused.status_code == 403 and "model.effect_modules" in refused.json()["detail"]
    allowed = _settings(tmp_path / "allowed", data)
    allowed.model.effect_modules = ["my_effects"]
    with (
        running(allowed, _memory(allowed)) as svc,
        httpx.Client(base_url=svc.http_url, timeout=60) as http,
    ):
        done = http.put("/wells/W01/model", json=body, headers=auth)
        state = http.get("/wells/W01").json()
    assert done.status_code == 200, done.text
    assert state["model"] == "mm+temperature_scale"
    assert "temperature_scale.k" in state["parameters"]


def test_model_config_accepts_effects(tmp_path: Any) -> None:
    from service.config import load_settings
    from vfm_core.errors import ConfigError

    cfg = load_settings(None, model={"name": "ham", "effects": "erosion, mpfm_bias"})
    assert cfg.model.effects == ["erosion", "mpfm_bias"]
    assert cfg.model.full_name == "ham+erosion+mpfm_bias"
    with pytest.raises(ConfigError, match="Effects extend the models mm, hem, ham, not 'lr'"):
        load_settings(None, model={"name": "lr", "effects": ["erosion"]})
    with pytest.raises(ConfigError, match="Unknown effect 'wear'"):
        load_settings(None, model={"name": "mm", "effects": ["wear"]})
