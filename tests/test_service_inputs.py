"""Checking inbound payloads and keys: every bad input gets its reason and a sentence."""

from __future__ import annotations

import json

import pytest

from service.errors import REASONS, InvalidRequest
from service.inputs import Counters, parse_measurement, parse_sensor, route_key

pytestmark = pytest.mark.timeout(60)

GOOD = {
    "time": "2020-01-01T00:00:00Z",
    "choke": 0.5,
    "p_up": 100.0,
    "p_down": 20.0,
    "t_up": 60.0,
    "eta_gas": 0.1,
    "eta_oil": 0.5,
}


def _with(**changes: object) -> bytes:
    data = {**GOOD, **changes}
    return json.dumps({k: v for k, v in data.items() if v is not ...}).encode()


SENSOR_CORPUS = [
    (b"{bad", "malformed JSON"),
    (b"\xff\xfe", "malformed JSON"),
    (b"[1, 2]", "not a JSON object"),
    (b"null", "not a JSON object"),
    (_with(p_up=...), "missing field"),
    (_with(choke="abc"), "wrong type"),
    (_with(choke=True), "wrong type"),
    (_with(t_up="NaN"), "wrong type"),
    (_with(time="yesterday"), "wrong type"),
    (_with(p_up=float("nan")), "not finite"),  # json.dumps writes NaN
    (_with(t_up=float("inf")), "not finite"),
    (_with(p_up=-5.0), "negative or zero pressure"),
    (_with(p_down=0.0), "negative or zero pressure"),
    (_with(p_down=150.0), "p_down >= p_up"),
    (_with(p_down=100.0), "p_down >= p_up"),
    (_with(choke=1.5), "choke outside 0..1"),
    (_with(choke=-0.1), "choke outside 0..1"),
    (_with(eta_gas=1.2), "fraction outside 0..1"),
    (_with(eta_gas=0.6, eta_oil=0.6), "fractions sum above 1"),
    (_with(t_up=-300.0), "temperature below absolute zero"),
]


@pytest.mark.parametrize(("payload", "reason"), SENSOR_CORPUS)
def test_bad_sensor_payloads(payload: bytes, reason: str) -> None:
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(payload)
    assert info.value.reason == reason
    assert reason in REASONS
    assert info.value.message.endswith(".") and len(info.value.message) > 15


#: inputs outside their physical span (vfm_core.sensor_faults.DEFAULT_RANGES), each alone:
#: taken raw while the service watches instrument faults (an out_of_range fault)
OUT_OF_SPAN = [
    {"p_up": -5.0},
    {"p_down": -1.0},
    {"p_down": 1600.0},  # above the span and above p_up
    {"p_up": -5.0, "p_down": -6.0},
    {"choke": 1.5},
    {"choke": -0.1},
    {"eta_gas": 1.2},
    {"eta_oil": -0.5},
    {"t_up": -300.0},
]


@pytest.mark.parametrize("changes", OUT_OF_SPAN)
def test_an_input_out_of_its_span_is_taken_raw_while_faults_are_watched(
    changes: dict[str, float],
) -> None:
    """``out_of_span=True`` (the service's intake while it watches instrument faults): the
    sample is taken with its raw values, in a block too; without it, refused as before."""
    from service.inputs import parse_sensor_block

    payload = _with(**changes)
    with pytest.raises(InvalidRequest):
        parse_sensor(payload)
    sample = parse_sensor(payload, out_of_span=True)
    assert sample.inputs() == [changes.get(k, v) for k, v in GOOD.items() if k != "time"]
    rows = [GOOD, {**GOOD, **changes, "time": "2020-01-01T00:01:00Z"}]
    block = {k: [r[k] for r in rows] for k in GOOD}
    taken = parse_sensor_block(block, 10, lambda t, what: None, 0, 2**62, out_of_span=True)
    assert taken.refused == [] and taken.inputs[1].tolist() == sample.inputs()
    refused = parse_sensor_block(block, 10, lambda t, what: None, 0, 2**62)
    assert [row for row, _ in refused.refused] == [1] and len(refused.times_ns) == 1


@pytest.mark.parametrize(
    ("changes", "reason"),
    [
        ({"p_down": 0.0}, "negative or zero pressure"),  # inside the span 0..1500 bar a
        ({"p_up": -5.0, "p_down": 0.0}, "negative or zero pressure"),
        ({"choke": 1.5, "p_down": 150.0}, "p_down >= p_up"),  # both in span: still wrong
        ({"eta_gas": 0.7, "eta_oil": 0.6, "t_up": -100.0}, "fractions sum above 1"),
        ({"choke": 2.0, "time": "yesterday"}, "wrong type"),
    ],
)
def test_out_of_span_takes_only_a_sample_whose_other_checks_pass(
    changes: dict[str, object], reason: str
) -> None:
    """The inputs outside their span are set aside; what is left must pass every check,
    and a sample refused is refused with the reason of what is left."""
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(_with(**changes), out_of_span=True)
    assert info.value.reason == reason


def test_good_sensor_payload() -> None:
    sample = parse_sensor(_with())
    assert sample.inputs() == [0.5, 100.0, 20.0, 60.0, 0.1, 0.5]
    assert sample.time.tzinfo is not None


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b'{"time": "2020-01-01", "q_total": -1}', "negative rate"),
        (b'{"time": "2020-01-01", "q_total": NaN}', "not finite"),
        (b'{"time": "2020-01-01", "q_total": "12"}', "wrong type"),
        (b'{"time": "2020-01-01"}', "missing field"),
        (b'{"time": "x", "q_total": 3}', "wrong type"),
    ],
)
def test_bad_measurement_payloads(payload: bytes, reason: str) -> None:
    with pytest.raises(InvalidRequest) as info:
        parse_measurement(payload)
    assert info.value.reason == reason


def test_keys() -> None:
    assert route_key("vfm", "vfm/W01/sensors") == ("W01", "sensors", None)
    assert route_key("vfm", "vfm/W01/measurements/mpfm") == ("W01", "measurements", "mpfm")
    assert route_key("vfm/a", "vfm/a/W01/measurements/well_test") == (
        "W01",
        "measurements",
        "well_test",
    )
    for key, reason in [
        ("vfm/W01", "unparseable key"),
        ("vfm/W01/sensors/extra", "unparseable key"),
        ("other/W01/sensors", "unparseable key"),
        ("vfm/W01/measurements/guess", "unknown source"),
    ]:
        with pytest.raises(InvalidRequest) as info:
            route_key("vfm", key)
        assert info.value.reason == reason


def test_counters_count_every_rejection_and_log_each_reason_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    counters = Counters()
    with caplog.at_level("WARNING", logger="vfm.service.inputs"):
        for _ in range(100):
            counters.reject("not finite", "p_up must be a finite number, got nan.")
        counters.reject("duplicate", "again.")
    snap = counters.snapshot()
    assert snap["rejected"] == {"not finite": 100, "duplicate": 1}
    assert len(caplog.records) == 2  # rate-limited: once per reason
