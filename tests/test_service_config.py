"""The service's settings: sources, validation sentences, loopback-only defaults."""

from __future__ import annotations

import json

import pytest

from service.config import Settings, endpoint_host, is_loopback_host, load_settings
from vfm_core.errors import ConfigError

pytestmark = pytest.mark.timeout(60)


def test_defaults_are_loopback_and_safe(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in [k for k in __import__("os").environ if k.startswith("VFM_")]:
        monkeypatch.delenv(key)
    s = load_settings()
    assert s.http.host == "127.0.0.1"
    assert s.zenoh.mode == "peer" and not s.zenoh.multicast_scouting
    assert all(is_loopback_host(endpoint_host(ep) or "") for ep in s.zenoh.listen)
    assert s.http.token is None
    assert s.prefix == "vfm" and s.model.name == "mm" and s.model.method == "ol"


def test_toml_file_then_env_override(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = tmp_path / "vfm.toml"
    cfg.write_text(
        '[model]\nname = "ham"\nmethod = "pbl:14d"\n[http]\nport = 8123\n[store]\npath = "data/s.sqlite"\n'
    )
    monkeypatch.setenv("VFM_HTTP__PORT", "9001")
    monkeypatch.setenv("VFM_ZENOH__CONNECT", '["tcp/127.0.0.1:7447"]')
    s = load_settings(cfg)
    assert (s.model.name, s.model.method) == ("ham", "pbl:14d")
    assert s.http.port == 9001  # the environment wins over the file
    assert s.zenoh.connect == ["tcp/127.0.0.1:7447"]
    assert s.store.path == tmp_path / "data" / "s.sqlite"  # relative to the file


def test_json_file(tmp_path) -> None:
    cfg = tmp_path / "vfm.json"
    cfg.write_text(json.dumps({"prefix": "vfm/field-a", "inputs": {"unknown_wells": "reject"}}))
    s = load_settings(cfg)
    assert s.prefix == "vfm/field-a" and s.inputs.unknown_wells == "reject"


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ({"model": {"name": "hamx"}}, ["model.name", "'hamx'", "last", "ham"]),
        (
            {"model": {"name": "mtl"}, "queues": {"workers": 2}},
            ["mtl", "field-wide", "queues.workers = 1"],
        ),
        ({"model": {"name": "mtl", "effects": ["erosion"]}}, ["model.effects", "mtl"]),
        ({"model": {"method": "pbl:xx"}}, ["model.method", "14d"]),
        ({"store": {"synchronous": "fast"}}, ["store.synchronous", "'fast'", "'full' or 'normal'"]),
        ({"inputs": {"unknown_wells": "maybe"}}, ["inputs.unknown_wells", "'create' or 'reject'"]),
        ({"zenoh": {"mode": "p2p"}}, ["zenoh.mode", "'peer', 'client' or 'router'"]),
        ({"prefix": "vfm/*"}, ["prefix", "wildcards"]),
        ({"bogus": 1}, ["'bogus' is unknown"]),
        ({"http": {"token": "short"}}, ["at least 16 characters"]),
        ({"zenoh": {"mode": "client", "connect": []}}, ["client", "zenoh.connect"]),
        ({"model": {"method": "pbl:auto"}}, ["pbl:auto", "drift.on_drift = 'retrain'"]),
    ],
)
def test_bad_values_stop_with_a_sentence(overrides: dict, expected: list[str]) -> None:
    with pytest.raises(ConfigError) as info:
        load_settings(None, **overrides)
    text = str(info.value)
    for part in expected:
        assert part in text, text
    assert text.endswith(".")


def test_non_loopback_binds_are_refused_unless_allowed() -> None:
    with pytest.raises(ConfigError, match="http.host = '0.0.0.0' is not a loopback address"):
        load_settings(None, http={"host": "0.0.0.0"})
    with pytest.raises(ConfigError, match="zenoh.allow_remote"):
        load_settings(None, zenoh={"listen": ["tcp/0.0.0.0:7447"]})
    s = load_settings(None, http={"host": "0.0.0.0", "allow_remote": True, "token": "x" * 20})
    assert s.http.host == "0.0.0.0"
    s = load_settings(None, zenoh={"listen": ["tcp/[::]:7447"], "allow_remote": True})
    assert s.zenoh.listen == ["tcp/[::]:7447"]
    assert load_settings(None, zenoh={"listen": ["tcp/[::1]:7447"]}).zenoh.listen == [
        "tcp/[::1]:7447"
    ]


def test_missing_or_unreadable_file(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_settings(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[model\nname=")
    with pytest.raises(ConfigError, match="cannot be read"):
        load_settings(bad)
    other = tmp_path / "vfm.yaml"
    other.write_text("a: 1")
    with pytest.raises(ConfigError, match=r"\.toml or \.json"):
        load_settings(other)


def test_token_is_masked() -> None:
    s = load_settings(None, http={"token": "t" * 20})
    assert s.public_dict()["http"]["token"] == "***"
    assert "tttt" not in repr(s)


def test_a_list_in_the_environment_that_is_not_json_gets_a_sentence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("VFM_ZENOH__CONNECT", "tcp/router:7447")
    with pytest.raises(ConfigError, match="as JSON"):
        load_settings(None)


def test_freeze_loaded_objects_leaves_them_out_of_collection() -> None:
    """`vfm serve` freezes what start-up loaded (queues.gc_freeze, on by default): a full
    collection then walks only what came after."""
    import gc

    from service.app import freeze_loaded_objects

    assert Settings().queues.gc_freeze is True
    assert Settings(queues={"gc_freeze": False}).queues.gc_freeze is False
    try:
        frozen = freeze_loaded_objects()
        assert frozen == gc.get_freeze_count() > 10_000  # torch, pandas, ... at least
        tracked_after = len(gc.get_objects())
        assert tracked_after < frozen  # the objects a full collection still walks
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0


def test_heap_freezer_freezes_what_stays_alive_and_frees_cycles_at_a_thaw() -> None:
    """`vfm serve` freezes again every queues.gc_refreeze_s: what was made and kept since
    (a well's recent samples) leaves the collector's full passes too. A frozen cycle that
    becomes garbage is freed at the next thaw (queues.gc_thaw_s), not kept for ever."""
    import gc
    import weakref

    from service.app import HeapFreezer, freeze_loaded_objects

    assert Settings().queues.gc_refreeze_s == 10.0
    assert Settings().queues.gc_thaw_s == 3600.0

    class Node:
        pass

    try:
        freeze_loaded_objects()
        freezer = HeapFreezer(every_s=10.0, thaw_s=100.0, now=0.0)
        kept = [[i, float(i)] for i in range(5_000)]  # what the service keeps (lists: tracked)
        cycle = Node()
        cycle.me = cycle  # type: ignore[attr-defined]
        alive = weakref.ref(cycle)
        assert any(o is kept for o in gc.get_objects())  # walked by a full pass now
        before = gc.get_freeze_count()
        assert freezer.tick(5.0) is False  # not yet due
        assert freezer.tick(10.0) is True
        assert freezer.freezes == 1 and freezer.thaws == 0
        assert gc.get_freeze_count() >= before + 5_000
        assert not any(o is kept for o in gc.get_objects())  # frozen: no longer walked
        del cycle
        gc.collect()
        assert alive() is not None  # frozen garbage cycle: not freed by a pass
        assert freezer.tick(15.0) is False
        assert freezer.tick(120.0) is True  # a thaw is due: unfreeze, collect, freeze
        assert freezer.thaws == 1
        assert alive() is None  # the cycle was freed
        assert kept[4_999] == [4_999, 4_999.0]  # what is alive stays
        assert HeapFreezer(every_s=0.0, thaw_s=1.0, now=0.0).tick(1e9) is False  # off
    finally:
        gc.unfreeze()
    assert gc.get_freeze_count() == 0


def test_a_serve_that_ends_at_start_is_reported_as_ended(tmp_path) -> None:
    """A bad setting ends `vfm serve` at once: its starter says so (with the exit code and
    the log's sentence) at once, not that it did not become ready within the timeout."""
    import time

    from service.testing import ServeProcess
    from vfm_core.errors import VFMError

    config = tmp_path / "vfm.toml"
    config.write_text('[model]\nname = "nosuch"\n', encoding="utf-8")
    started = time.monotonic()
    with pytest.raises(VFMError) as caught:
        ServeProcess(config, tmp_path / "serve.log").start(timeout=120)
    message = str(caught.value)
    assert "ended (exit code" in message and "unknown model 'nosuch'" in message
    assert "within" not in message and time.monotonic() - started < 60
