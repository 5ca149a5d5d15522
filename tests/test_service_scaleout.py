"""Scale-out: several `vfm serve` instances behind a router, each owning a set of wells.

The router is a Python Zenoh session in router mode (zenohd is not installable here),
the instances are real `vfm serve` subprocesses (spawned, never forked after Zenoh
opened), and one replay of a small simulated field feeds them all through the router.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pandas as pd
import pytest
import zenoh

from replay.replayer import replay_frame
from service.app import running
from service.config import load_settings
from service.scaleout import WellSet, list_instances, overlapping, pattern_chunk
from service.testing import READY, ServeProcess, loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.errors import ConfigError, VFMError
from vfm_core.messages import SensorSample, sensors_key
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(180)

SPLIT = "2016-11-01"
CUT = pd.Timestamp("2016-12-01", tz="UTC")
A_WELLS, B_WELLS = ["*1", "*3"], ["*2", "*4"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _router(port: int) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(cfg)


def _client(port: int) -> zenoh.Session:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(cfg)


# -- the patterns -----------------------------------------------------------------------------
def test_patterns_match_whole_ids_and_map_to_zenoh_chunks() -> None:
    own = WellSet(["W0*", "*-north", "X"])
    assert "W01" in own and "W0" in own and "A-north" in own and "X" in own
    assert "W10" not in own and "XW0" not in own and "X1" not in own
    assert WellSet([]).everything and "anything" in WellSet([])
    assert own.key_exprs("vfm/field-a") == [
        "vfm/field-a/W0$*/**",
        "vfm/field-a/$*-north/**",
        "vfm/field-a/X/**",
    ]
    assert WellSet([]).key_exprs("vfm") == ["vfm/**"]
    assert pattern_chunk("**") == "*" and pattern_chunk("a**b") == "a$*b"
    assert overlapping(["W0*"], ["W1*"]) is None
    assert overlapping(["W0*"], ["*1"]) == ("W0*", "*1")  # W01 matches both
    assert overlapping([], ["W1*"]) == ("*", "W1*")  # no patterns: every well


def test_bad_or_overlapping_patterns_stop_the_service_with_a_sentence(tmp_path: Path) -> None:
    store = {"path": str(tmp_path / "s.sqlite")}
    assert load_settings(None, zenoh={"wells": "W0*, W1*"}, store=store).zenoh.wells == [
        "W0*",
        "W1*",
    ]
    with pytest.raises(ConfigError, match="'W0\\*' and 'W\\*1' match the same well ids"):
        load_settings(None, zenoh={"wells": ["W0*", "W*1"]}, store=store)
    with pytest.raises(ConfigError, match="not a well id in which \\* stands"):
        load_settings(None, zenoh={"wells": ["W/0*"]}, store=store)
    with pytest.raises(ConfigError, match="inputs.wells names W1, outside"):
        load_settings(None, zenoh={"wells": ["W0*"]}, inputs={"wells": ["W1"]}, store=store)


def test_a_message_of_another_instances_well_is_refused_and_counted(tmp_path: Path) -> None:
    settings = loopback_settings(tmp_path, zenoh={"wells": ["W0*"]})
    sample = SensorSample(
        time=pd.Timestamp.now(tz="UTC").floor("s").to_pydatetime(),
        choke=0.5,
        p_up=100.0,
        p_down=30.0,
        t_up=60.0,
        eta_gas=0.3,
        eta_oil=0.6,
    ).model_dump_json()
    transport = MemoryTransport()
    with running(settings, transport) as svc:
        transport.put(sensors_key("vfm", "W11"), sample)  # reaches it anyway: no router here
        transport.put(sensors_key("vfm", "W01"), sample)
        wait_until(lambda: "W01" in svc.engine.wells, 10, "W01 created")
        with httpx.Client(base_url=svc.http_url, timeout=10) as http:
            health = http.get("/health").json()
            assert health["rejected"] == {"well of another instance": 1}
            assert health["owned_wells"] == "W0*" and health["zenoh"]["wells"] == ["W0*"]
            assert [w["well"] for w in http.get("/wells").json()] == ["W01"]
            r = http.get("/wells/W11")
            assert r.status_code == 404
            assert "not served by this instance, which owns the wells W0*" in r.json()["detail"]
            assert http.get("/wells/W02").json()["detail"].startswith("The well 'W02' is not known")
        last = svc.service.counters.snapshot()
    assert sum(last["accepted"].values()) >= 1


def test_the_compose_instances_have_valid_disjoint_wells(monkeypatch: pytest.MonkeyPatch) -> None:
    root = Path(__file__).resolve().parents[1]
    compose = (root / "docker" / "compose.yaml").read_text()
    sets = [json.loads(v) for v in re.findall(r"VFM_ZENOH__WELLS: '(.*)'", compose)]
    stores = re.findall(r"VFM_STORE__PATH: (\S+)", compose)
    assert len(sets) == 2 and len(set(stores)) == 2  # two instances, a store each
    assert overlapping(sets[0], sets[1]) is None
    monkeypatch.setenv("VFM_HTTP__TOKEN", "a-token-for-the-container-0123")
    for wells, store in zip(sets, stores, strict=True):
        monkeypatch.setenv("VFM_ZENOH__WELLS", json.dumps(wells))
        monkeypatch.setenv("VFM_STORE__PATH", store)
        s = load_settings(root / "docker" / "vfm.toml")
        assert s.zenoh.wells == wells and str(s.store.path) == store
    owners = [[w for w in ("W01", "W02", "W03", "W04", "W05") if w in WellSet(s)] for s in sets]
    assert sorted(owners[0] + owners[1]) == ["W01", "W02", "W03", "W04", "W05"]


def test_vfm_instances_says_what_is_wrong_with_its_arguments(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from vfm_core.cli import main

    assert main(["instances", "--connect", "nonsense"]) == 2
    assert "--connect nonsense is not a Zenoh endpoint list" in capsys.readouterr().err
    assert main(["instances", "--well", "W/1"]) == 2
    assert "cannot be used in a key expression" in capsys.readouterr().err


# -- two instances behind a router --------------------------------------------------------------
def _config(folder: Path, data: Path, router: int, wells: list[str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    cfg = folder / "vfm.toml"
    cfg.write_text(f"""
[model]
name = "mm"
method = "ol"
history = "{data}"
history_until = "{SPLIT}"
[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:{router}"]
listen = []
wells = {json.dumps(wells)}
[http]
port = 0
[store]
path = "{folder / "store.sqlite"}"
synchronous = "normal"
""")
    return cfg


def _updates(http: str) -> dict[str, int]:
    return {w["well"]: w["n_updates"] for w in httpx.get(f"{http}/wells", timeout=10).json()}


def _published(http: str) -> int:
    return int(httpx.get(f"{http}/health", timeout=10).json()["predictions_published"])


def test_two_instances_share_a_field_and_one_keeps_serving_when_the_other_dies(
    tmp_path: Path,
) -> None:
    frame = validate_frame(simulate_field(wells=4, years=1, seed=0).observations).frame
    data = tmp_path / "field.parquet"
    frame.to_parquet(data)
    port = _free_port()
    router = _router(port)
    a = b = None
    try:
        a = ServeProcess(_config(tmp_path / "a", data, port, A_WELLS), tmp_path / "a.log").start()
        b = ServeProcess(_config(tmp_path / "b", data, port, B_WELLS), tmp_path / "b.log").start()
        first = frame[frame["time"] < CUT]
        result = replay_frame(
            first,
            connect=[f"tcp/127.0.0.1:{port}"],
            mode="client",
            start=SPLIT,
            progress=False,
            idle_timeout=2.0,
        )
        sent = first[first["time"] >= pd.Timestamp(SPLIT, tz="UTC")]
        n_samples = len(sent)
        assert result.samples_sent == n_samples and result.missing == 0
        assert result.predictions_received == n_samples

        # every well answered by exactly one instance: each published its own wells' samples
        in_a = sent["well"].isin(["W01", "W03"])
        assert _published(a.http_url) == int(in_a.sum())
        assert _published(b.http_url) == int((~in_a).sum())
        for proc, mine, theirs in ((a, ["W01", "W03"], "W02"), (b, ["W02", "W04"], "W01")):
            wells = httpx.get(f"{proc.http_url}/wells", timeout=10).json()
            assert sorted(w["well"] for w in wells) == mine
            other = b if proc is a else a
            r = httpx.get(f"{proc.http_url}/wells/{theirs}", timeout=10)
            assert r.status_code == 404 and f"{other.http_url}/wells/{theirs}" in r.json()["detail"]
            health = httpx.get(f"{proc.http_url}/health", timeout=10).json()
            assert health["rejected_total"] == 0

        # who serves what: the instances answer <prefix>/@instances/*, `vfm instances` prints it
        with _client(port) as session:
            claims = list_instances(session, "vfm")
        assert [(c.wells, c.http) for c in claims] == [
            (A_WELLS, a.http_url),
            (B_WELLS, b.http_url),
        ]
        out = subprocess.run(
            [sys.executable, "-m", "vfm_core.cli", "instances", "--connect"]
            + [f"tcp/127.0.0.1:{port}", "--well", "W04", "--json"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert out.returncode == 0, out.stderr
        assert [c["http"] for c in json.loads(out.stdout)] == [b.http_url]

        # a third instance claiming a well of another one refuses to start
        with pytest.raises(VFMError, match="already owns wells under 'vfm'"):
            ServeProcess(_config(tmp_path / "c", data, port, ["W0*"]), tmp_path / "c.log").start(
                timeout=60
            )

        # B dies (SIGKILL): its wells go unanswered, A keeps serving its own
        b_updates = _updates(b.http_url)
        assert all(n > 0 for n in b_updates.values())  # it learned from the replay's MPFM
        b.kill9()
        with _client(port) as session:
            wait_until(lambda: len(list_instances(session, "vfm", timeout=1.0)) == 1, 20, "B gone")
        later = frame[(frame["time"] >= CUT) & frame["well"].isin(["W01", "W03"])]
        again = replay_frame(
            later,
            connect=[f"tcp/127.0.0.1:{port}"],
            mode="client",
            progress=False,
            idle_timeout=2.0,
        )
        assert again.samples_sent == len(later) > 0 and again.missing == 0
        assert _published(a.http_url) == int(in_a.sum()) + len(later)
        r = httpx.get(f"{a.http_url}/wells/W02", timeout=10)
        assert r.status_code == 404 and "no running instance" in r.json()["detail"]

        # B restarts from its store: its wells are back, with the updates they had learned
        b = ServeProcess(_config(tmp_path / "b", data, port, B_WELLS), tmp_path / "b.log").start()
        ready = [
            line for line in (tmp_path / "b.log").read_text().splitlines() if READY.search(line)
        ]
        assert ready[-1].endswith("owns=*2,*4")
        assert _updates(b.http_url) == b_updates
    finally:
        for proc in (a, b):
            if proc is not None:
                proc.stop()
        router.close()
