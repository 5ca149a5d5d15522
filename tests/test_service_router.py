"""The deployment of docker/compose.yaml in miniature: service and replay as clients of a router.

zenohd is not installable here; a Python session in ``router`` mode routes the same way.
Also checks that docker/vfm.toml is a valid configuration.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pandas as pd
import pytest
import zenoh

from replay.replayer import replay_frame
from service.app import running
from service.config import load_settings
from service.testing import loopback_settings
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_docker_config_is_valid(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VFM_HTTP__TOKEN", "a-token-for-the-container-0123")
    s = load_settings(ROOT / "docker" / "vfm.toml")
    assert s.zenoh.mode == "client" and s.zenoh.connect == ["tcp/router:7447"]
    assert s.http.host == "0.0.0.0" and s.http.allow_remote and s.http.token is not None
    assert str(s.store.path) == "/data/store.sqlite"
    compose = (ROOT / "docker" / "compose.yaml").read_text()
    assert '--mode", "client"' in compose and "tcp/router:7447" in compose


def test_service_and_replay_as_clients_of_a_router(tmp_path: Path) -> None:
    port = _free_port()
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    router = zenoh.open(cfg)
    try:
        frame = validate_frame(simulate_field(wells=1, years=1, seed=0).observations).frame
        data = tmp_path / "field.parquet"
        frame.to_parquet(data)
        settings = loopback_settings(
            tmp_path,
            zenoh={"mode": "client", "connect": [f"tcp/127.0.0.1:{port}"], "listen": []},
            model={
                "name": "mm",
                "method": "ol",
                "history": str(data),
                "history_until": "2016-11-01",
            },
        )
        with running(settings):
            result = replay_frame(
                frame,
                connect=[f"tcp/127.0.0.1:{port}"],
                mode="client",
                start="2016-11-01",
                progress=False,
                idle_timeout=1.0,
            )
        n = int((frame["time"] >= pd.Timestamp("2016-11-01", tz="UTC")).sum())
        assert result.samples_sent == n and result.missing == 0
        assert result.overall_mape < 10
    finally:
        router.close()
