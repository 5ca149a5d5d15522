"""The engine's real code path without a network: inputs through the in-memory transport.

``Service`` owns the store, the engine and a ``MemoryTransport``; the shared field client
sends on it exactly as it does on Zenoh, and the transport hands every input to the
engine's receiver path (``deliver``). No HTTP here: the engine's answers are domain errors.
The model is ``last`` (the latest measured rate), so every number is known by hand.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest

from replay.client import FieldClient, sample_of
from service.app import Service
from service.engine import Engine
from service.errors import InvalidRequest, NotAllowed, UnknownWell
from service.store import HistoryMeasurement, Store
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement
from vfm_core.timeutil import iso, to_ns

pytestmark = pytest.mark.timeout(120)

T0 = datetime(2020, 3, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


@dataclass
class Rig:
    service: Service
    bus: MemoryTransport
    client: FieldClient

    @property
    def engine(self) -> Engine:
        assert self.service.engine is not None
        return self.service.engine

    @property
    def store(self) -> Store:
        assert self.service.store is not None
        return self.service.store

    def measurements(self, well: str) -> list[HistoryMeasurement]:
        return self.store.history(well, 0, 2**62, 1000)[1]

    def rejected(self) -> dict[str, int]:
        return self.service.counters.snapshot()["rejected"]


@contextmanager
def rig(folder: Path, **overrides: Any) -> Iterator[Rig]:
    settings = loopback_settings(folder, model={"name": "last", "method": "ol"}, **overrides)
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            yield Rig(service, bus, client)
    finally:
        service.stop()


def test_a_measurement_waits_for_its_sample_then_is_learned(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        # the measurement comes first: stored as pending, the well created on first sight
        r.client.send_measurement("W01", "mpfm", Measurement(time=T0, q_total=1500.0))
        r.client.send_sample("W01", sample_of(T0 + timedelta(seconds=60), INPUTS))
        # the next sample is answered with what was learned (model `last`: the latest rate)
        later = T0 + timedelta(minutes=10)
        r.client.send_sample("W01", sample_of(later, INPUTS))
        assert r.client.wait_for_prediction("W01", later) == pytest.approx(1500.0)
        (m,) = r.measurements("W01")
        assert (m.status, m.source, m.via) == ("learned", "mpfm", "zenoh")
        assert m.sample_time_ns == to_ns(T0 + timedelta(seconds=60))
        assert m.predicted is None  # no model yet when that sample was predicted
        assert r.client.prediction("W01", T0 + timedelta(seconds=60)) is None
        # the prediction went out on the well's prediction key, recorded by the transport
        assert [k for k, _ in r.bus.published] == ["vfm/W01/prediction"]
        view = r.engine.well_view("W01")
        assert view["version"] == 1 and view["pending_measurements"] == 0
        assert view["last_sample_time"] == iso(to_ns(later))


def test_a_measurement_without_a_sample_in_tolerance_is_stored_unpaired(tmp_path: Path) -> None:
    with rig(tmp_path, inputs={"pending_timeout_s": 0.2}) as r:
        r.client.send_sample("W01", sample_of(T0, INPUTS))
        far = T0 + timedelta(days=10)
        r.client.send_measurement("W01", "mpfm", Measurement(time=far, q_total=900.0))
        wait_until(
            lambda: r.measurements("W01") and r.measurements("W01")[0].status == "unpaired",
            10,
            "the wait to run out",
        )
        assert r.rejected() == {"no sensor sample within tolerance": 1}
        # a measurement older than the latest sample with no sample near it is refused outright
        r.client.send_sample("W01", sample_of(T0 + timedelta(days=20), INPUTS))
        r.client.send_measurement(
            "W01", "mpfm", Measurement(time=T0 + timedelta(days=15), q_total=1.0)
        )
        wait_until(
            lambda: r.rejected().get("no sensor sample within tolerance") == 2, 10, "the refusal"
        )
        assert len(r.measurements("W01")) == 1  # not stored


def test_samples_in_order_only_and_once(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        r.client.send_sample("W01", sample_of(T0, INPUTS))
        r.client.send_sample("W01", sample_of(T0, INPUTS))  # again
        r.client.send_sample("W01", sample_of(T0 - timedelta(minutes=1), INPUTS))  # older
        r.client.put_raw("vfm/W01/sensors", b"{broken")
        wait_until(lambda: sum(r.rejected().values()) == 3, 10, "three refusals")
        assert r.rejected() == {"duplicate": 1, "time going backwards": 1, "malformed JSON": 1}
        assert r.service.counters.snapshot()["accepted"] == {"sensors": 1}


def test_well_ids_follow_the_one_rule(tmp_path: Path) -> None:
    """A well created on first sight needs a valid id, as in files, keys and the config."""
    with rig(tmp_path) as r:
        r.client.put_raw("vfm/ W02/sensors", sample_of(T0, INPUTS).model_dump_json())
        # '@' first: Zenoh matches such a chunk with no wildcard, so no subscriber of
        # vfm/** would ever see the well's predictions
        r.client.put_raw("vfm/@W04/sensors", sample_of(T0, INPUTS).model_dump_json())
        r.client.send_sample("W01", sample_of(T0, INPUTS))
        wait_until(lambda: r.rejected().get("unparseable key") == 2, 10, "the refusals")
        assert set(r.engine.wells) == {"W01"}
        with pytest.raises(InvalidRequest, match="starts or ends with a space") as info:
            r.engine.submit_well_test("W03 ", Measurement(time=T0, q_total=1.0))
        assert info.value.reason == "unparseable key"
        with pytest.raises(InvalidRequest, match="starts with '@'") as info:
            r.engine.submit_well_test("@W05", Measurement(time=T0, q_total=1.0))
        assert info.value.reason == "unparseable key"


def test_the_engine_refuses_with_domain_errors(tmp_path: Path) -> None:
    with rig(tmp_path, inputs={"unknown_wells": "reject", "wells": ["W01"]}) as r:
        with pytest.raises(UnknownWell) as unknown:
            r.engine.submit_well_test("W09", Measurement(time=T0, q_total=1.0))
        assert unknown.value.reason == "unknown well"
        with pytest.raises(UnknownWell) as read:
            r.engine.well_view("W09")
        assert read.value.reason is None  # a read refuses no input
        with pytest.raises(NotAllowed, match="model.effect_modules"):
            r.engine.change_model("W01", "mm", ["my_effects:TemperatureScale"])
        with pytest.raises(InvalidRequest, match="Unknown effect 'erosoin'"):
            r.engine.change_model("W01", "mm", ["erosoin"])
        with pytest.raises(UnknownWell):
            r.engine.change_model("W09")
        assert not hasattr(unknown.value, "status")


def test_a_well_test_is_stored_then_learned(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        r.client.send_sample("W01", sample_of(T0, INPUTS))
        r.client.send_measurement("W01", "mpfm", Measurement(time=T0, q_total=1000.0))
        r.client.send_sample("W01", sample_of(T0 + timedelta(hours=1), INPUTS))
        r.client.wait_for_prediction("W01", T0 + timedelta(hours=1))
        # a well test just before the latest sample pairs with it at once
        result = r.engine.submit_well_test(
            "W01", Measurement(time=T0 + timedelta(minutes=59, seconds=30), q_total=1100.0)
        ).result(10)
        assert (result.status, result.version_before, result.version_after) == ("learned", 1, 2)
        assert result.before["q_total"] == pytest.approx(1000.0)
        assert result.after["q_total"] == pytest.approx(1100.0)
        assert result.paired_sample_time == iso(to_ns(T0 + timedelta(hours=1)))
        statuses = {(m.source, m.via, m.status) for m in r.measurements("W01")}
        assert statuses == {("mpfm", "zenoh", "learned"), ("well_test", "http", "learned")}
        # one after the latest sample waits for the next one
        waiting = r.engine.submit_well_test(
            "W01", Measurement(time=T0 + timedelta(hours=1, seconds=30), q_total=1200.0)
        ).result(10)
        assert (waiting.status, waiting.version_after) == ("pending", 2)
        r.client.send_sample("W01", sample_of(T0 + timedelta(hours=1, minutes=2), INPUTS))
        r.client.send_sample("W01", sample_of(T0 + timedelta(hours=2), INPUTS))
        assert r.client.wait_for_prediction("W01", T0 + timedelta(hours=2)) == pytest.approx(1200.0)


def test_a_field_client_collects_only_the_wells_it_names(tmp_path: Path) -> None:
    """``FieldClient(wells=...)`` subscribes to those wells' predictions only (a plant timing
    one well need not parse every other well's answers)."""
    from vfm_core.errors import ConfigError

    with rig(tmp_path) as r:
        with pytest.raises(ConfigError, match="one key chunk"):
            FieldClient(r.bus, "vfm", wells="W01/x")
        with FieldClient(r.bus, "vfm", wells="W02") as only:
            for well, q in (("W01", 1000.0), ("W02", 2000.0)):
                r.client.send_measurement(well, "mpfm", Measurement(time=T0, q_total=q))
                r.client.send_sample(well, sample_of(T0, INPUTS))
            later = T0 + timedelta(minutes=10)
            for well in ("W01", "W02"):
                r.client.send_sample(well, sample_of(later, INPUTS))
            assert r.client.wait_for_prediction("W01", later) == pytest.approx(1000.0)
            assert r.client.wait_for_prediction("W02", later) == pytest.approx(2000.0)
            assert only.wait_for_prediction("W02", later) == pytest.approx(2000.0)
            assert only.prediction("W01", later) is None
            assert {w for w, _ in only.predictions} == {"W02"}
