"""The service's limits, one rule at a time: times, sizes, depth, ids in logs, rates, the
method rule, the per-well fair queue, well admission, retrain budgets and catch-up, the
store's schema migration.

Each test feeds the rule inputs on both sides of its bound and checks the answer (a
counted reason and a sentence, or acceptance); the engine tests run the real receiving
path over the in-memory transport.
"""

from __future__ import annotations

import json
import logging
import sqlite3
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import torch

from replay.client import FieldClient, sample_of
from service.app import Service
from service.config import load_settings, method_problem
from service.engine.fairqueue import CLOSED, FairQueue
from service.engine.learners import new_learner
from service.engine.learning import Learning
from service.engine.registry import Registry, TokenBucket
from service.engine.state import WellState
from service.errors import REASONS, InvalidRequest, UnknownWell
from service.inputs import Counters, Limits, parse_measurement, parse_sensor, printable
from service.store import SCHEMA_VERSION, AddWell, InsertParameters, Store
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.errors import ConfigError
from vfm_core.messages import Measurement, SensorSample
from vfm_core.timeutil import PLAUSIBLE_MIN, time_problem, to_ns

pytestmark = pytest.mark.timeout(120)

GOOD = {
    "time": "2020-01-01T00:00:00Z",
    "choke": 0.5,
    "p_up": 100.0,
    "p_down": 20.0,
    "t_up": 60.0,
    "eta_gas": 0.1,
    "eta_oil": 0.5,
}
T0 = datetime(2020, 3, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -

OUT_OF_RANGE = [
    "9999-12-31T23:59:59-14:00",
    "0001-01-01T00:00:00+14:00",
    "1000-01-01T00:00:00Z",
    "1677-09-21T00:00:00Z",
    "2262-04-12T00:00:00Z",
    "2500-01-01T00:00:00Z",
]


# -- times -------------------------------------------------------------------------------------
@pytest.mark.parametrize("text", OUT_OF_RANGE)
def test_times_outside_the_representable_span_are_refused_with_their_reason(text: str) -> None:
    for parse, data in (
        (parse_sensor, {**GOOD, "time": text}),
        (parse_measurement, {"time": text, "q_total": 10.0}),
    ):
        with pytest.raises(InvalidRequest) as info:
            parse(json.dumps(data))
        assert info.value.reason == "time out of range"
        assert "1677-09-22" in info.value.message and info.value.message.endswith(".")


def test_time_problem_bounds() -> None:
    assert time_problem(datetime(2020, 1, 1)) is None  # naive = UTC
    assert time_problem(datetime(1969, 12, 31, tzinfo=UTC)) is None  # representable ...
    late = time_problem(datetime(1969, 12, 31, tzinfo=UTC), earliest=PLAUSIBLE_MIN)
    assert late is not None and "earliest plausible" in late  # ... but not plausible
    ahead = datetime(2030, 1, 1, tzinfo=UTC)
    assert time_problem(ahead, latest=datetime(2029, 1, 1, tzinfo=UTC)) is not None
    assert SensorSample.model_validate({**GOOD, "time": "2262-04-09T00:00:00Z"}).time.year == 2262


# -- sizes, depth, numbers -----------------------------------------------------------------------
def test_payload_size_and_json_depth_limits() -> None:
    limits = Limits(max_bytes=4096, max_depth=8)
    big = json.dumps({**GOOD, "pad": "x" * 5000})
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(big, limits)
    assert info.value.reason == "payload too large"
    assert parse_sensor(big, Limits(max_bytes=8192)).p_up == 100.0  # under the limit: fine
    nested = json.dumps({**GOOD, "extra": [[[[[[[[[[1]]]]]]]]]]})
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(nested, limits)
    assert info.value.reason == "too deeply nested"
    assert parse_sensor(nested).p_up == 100.0  # within the default depth: extra ignored
    # deeper than Python's recursion limit, within the size limit: refused, not a crash
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(b"[" * 50_000)
    assert info.value.reason == "too deeply nested"
    with pytest.raises(InvalidRequest) as info:
        parse_measurement(b"[" * 100_000)
    assert info.value.reason == "payload too large"


def test_huge_integers_are_not_finite_numbers() -> None:
    with pytest.raises(InvalidRequest) as info:
        parse_sensor(json.dumps({**GOOD, "p_up": 10**400}))
    assert info.value.reason == "not finite" and "digits" in info.value.message
    with pytest.raises(InvalidRequest) as info:
        parse_measurement(json.dumps({"time": GOOD["time"], "q_total": 10**400}))
    assert info.value.reason == "not finite"


def test_log_lines_cannot_be_forged(caplog: pytest.LogCaptureFixture) -> None:
    forged = "W01\nERROR vfm.service: forged line\x00\u2028"
    assert "\n" not in printable(forged) and "\\n" in printable(forged)
    assert len(printable("x" * 10_000)) < 300
    counters = Counters()
    with caplog.at_level(logging.WARNING, logger="vfm.service.inputs"):
        counters.reject("unparseable key", f"The key {forged} is bad.", where=f"vfm/{forged}")
    text = caplog.text
    assert "forged line" in text  # shown, escaped, on the one log line
    assert not any(line.startswith("ERROR vfm.service: forged") for line in text.splitlines())
    assert "\x00" not in text and "\u2028" not in text


# -- the method rule -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("method", "bad"),
    [
        ("ol", False),
        ("pbl:30d", False),
        ("pbl:1h", False),
        ("pbl:182d:window=365d", False),
        ("pbl:1ns", True),
        ("pbl:59min", True),
        ("pbl:auto", True),
        ("pbl:auto:alpha=0.05", True),
        ("nope", True),
    ],
)
def test_one_method_rule_for_config_and_http(method: str, bad: bool) -> None:
    problem = method_problem(method, 3600.0)
    assert (problem is not None) == bad, problem
    if bad:
        assert problem is not None and problem.endswith(".")
        with pytest.raises(ConfigError):
            load_settings(None, model={"method": method})
    else:
        assert load_settings(None, model={"method": method}).model.method == method
    # the minimum period is a setting
    assert method_problem("pbl:1ns", 0.0) is None


# -- the fair queue --------------------------------------------------------------------------------
def test_fair_queue_serves_wells_in_turn_and_keeps_each_wells_order() -> None:
    q = FairQueue(capacity=100, well_capacity=50)
    for i in range(20):
        assert q.put("flood", ("flood", i)) == "ok"
    assert q.put("quiet", ("quiet", 0)) == "ok"
    got = [q.get_nowait() for _ in range(4)]
    # the quiet well's one item comes second, not after the flood's 20
    assert got[:2] == [("flood", 0), ("quiet", 0)]
    assert got[2:] == [("flood", 1), ("flood", 2)]
    rest = []
    while (item := q.get_nowait()) is not None:
        rest.append(item)
    assert rest == [("flood", i) for i in range(3, 20)]


def test_a_separators_wells_share_one_fifo_in_arrival_order() -> None:
    """The wells of a separator (and its readings) are taken in the order they arrived, not
    in turn, so that a reading at t finds each partner's sample at t (walk57); a FIFO holds
    ``well_capacity`` per member; other wells keep their turns."""
    members = {"A": "SEP", "B": "SEP", "SEP": "SEP"}
    q = FairQueue(
        capacity=100,
        well_capacity=2,
        fifo_of=lambda well: members.get(well, well),
        fifo_capacity=lambda fifo: 2 * 2 if fifo == "SEP" else 2,
    )
    for item in [("A", 1), ("A", 2), ("B", 1), ("SEP", 1)]:
        assert q.put(item[0], item) == "ok"
    assert q.put("X", ("X", 1)) == "ok"
    assert q.put("B", ("B", 2), timeout=0.0) == "well"  # 2 members x 2 = 4 items held
    assert q.depth("A") == q.depth("B") == q.depth("SEP") == 4
    got = [q.get_nowait() for _ in range(5)]
    # SEP's FIFO in arrival order, X in its turn between (round robin over FIFOs)
    assert got == [("A", 1), ("X", 1), ("A", 2), ("B", 1), ("SEP", 1)]


def test_fair_queue_get_many_takes_what_get_nowait_would() -> None:
    """A worker takes items a few at a time: the same items in the same order, the room
    they free counted (a block by its weight), a waiting sender woken, CLOSED at the end."""
    one, many = FairQueue(capacity=200, well_capacity=50), FairQueue(capacity=200, well_capacity=50)
    for q in (one, many):
        for i in range(30):
            q.put("flood", ("flood", i))
            if i % 3 == 0:
                q.put(f"w{i}", (f"w{i}", i), weight=1 + i % 4)
    order = []
    while (item := one.get_nowait()) is not None:
        order.append(item)
    taken = []
    for limit in [1, 5, 16, 3, 100]:
        taken.extend(many.get_many(limit))
    assert taken == order and many.qsize() == 0 and many.get_many(16) == []
    full = FairQueue(capacity=4, well_capacity=10)
    for i in range(4):
        full.put("a", i)
    result: list[str] = []
    t = threading.Thread(target=lambda: result.append(full.put("b", 9, timeout=5.0)))
    t.start()
    time.sleep(0.05)
    assert full.get_many(2) == [0, 1]  # room for the waiting sender at once
    t.join(5)
    assert result == ["ok"] and full.qsize() == 3
    full.close()
    assert full.get_many(16) == [2, 9, 3]  # the wells in turn
    assert full.get_many(16) == [CLOSED]


def test_fair_queue_bounds_and_close() -> None:
    q = FairQueue(capacity=5, well_capacity=3)
    assert [q.put("a", i) for i in range(3)] == ["ok"] * 3
    assert q.put("a", 3, timeout=0.05) == "well"  # the well's own FIFO is full
    assert [q.put("b", i) for i in range(2)] == ["ok"] * 2
    assert q.put("c", 0, timeout=0.05) == "total"  # the worker's queue is full
    assert q.put("c", 0, force=True) == "ok"  # a swap is never dropped
    # a waiting put goes through as soon as the worker takes an item of that well
    result: list[str] = []
    t = threading.Thread(target=lambda: result.append(q.put("b", 9, timeout=5.0)))
    t.start()
    time.sleep(0.05)
    assert q.get_nowait() == 0  # a's first ...
    assert q.get_nowait() == 0  # ... then b's: the queue has room again
    t.join(5)
    assert result == ["ok"]
    q.close()
    assert sorted(q.drain()) == [0, 1, 1, 2, 9]
    assert q.get(timeout=0.1) is CLOSED


def test_fair_queue_counts_a_block_by_its_samples() -> None:
    """The queue bounds the samples it holds: a sensor block weighs its samples."""
    q = FairQueue(capacity=100, well_capacity=50)
    assert q.put("a", "block of 60", weight=60) == "ok"
    assert q.put("b", "block of 50", weight=50, timeout=0.05) == "total"
    assert q.put("b", "sample") == "ok"
    assert q.qsize() == 61
    assert q.get_nowait() == "block of 60"
    assert q.put("b", "block of 50", weight=50) == "ok"
    assert q.qsize() == 51
    # a block heavier than the whole queue goes in once the queue is empty
    assert q.put("c", "block of 500", weight=500, timeout=0.05) == "total"
    assert [q.get_nowait(), q.get_nowait()] == ["sample", "block of 50"]
    assert q.put("c", "block of 500", weight=500) == "ok" and q.qsize() == 100


# -- admission of wells ----------------------------------------------------------------------------
def test_registry_caps_wells_and_their_creation_rate(tmp_path: Path) -> None:
    settings = loopback_settings(
        tmp_path,
        inputs={"max_wells": 5, "new_wells_per_s": 1.0, "new_wells_burst": 3},
    )
    reg = Registry(settings, {})
    for w in ("A", "B", "C"):
        reg.admit(w)
    with pytest.raises(InvalidRequest) as info:
        reg.admit("D")  # the burst is used up
    assert info.value.reason == "too many new wells"
    reg.admit("A")  # a known (being created) well passes
    with pytest.raises(UnknownWell) as unknown:
        reg.admit("E", create=False)  # HTTP never creates a well
    assert unknown.value.reason == "unknown well"
    time.sleep(2.1)
    reg.admit("D")
    reg.admit("E")
    with pytest.raises(InvalidRequest) as info:
        reg.admit("F")
    assert info.value.reason == "too many wells" and "inputs.max_wells" in info.value.message
    reg.retiring("A", time.time_ns())
    with pytest.raises(InvalidRequest) as info:
        reg.admit("A")
    assert info.value.reason == "retired well"


def test_per_well_quota(tmp_path: Path) -> None:
    reg = Registry(loopback_settings(tmp_path, inputs={"well_rate_hz": 5.0, "well_burst": 10}), {})
    refused = 0
    for _ in range(30):
        try:
            reg.quota("A")
        except InvalidRequest as exc:
            assert exc.reason == "well flooding"
            refused += 1
    assert 15 <= refused <= 20  # a burst of 10 (and a token or two refilled), the rest refused
    reg.quota("B")  # another well has its own quota
    # a sensor block counts its samples: 8 of the burst of 10, then 8 more are refused
    reg.quota("C", 8)
    with pytest.raises(InvalidRequest, match="sensor block of 8 samples") as info:
        reg.quota("C", 8)
    assert info.value.reason == "well flooding"
    reg.quota("D", 50)  # a block above the burst passes once the burst is saved up
    with pytest.raises(InvalidRequest):
        reg.quota("D", 1)
    # ... and the well repays it: a block of 1,000 at 1/s, then nothing for 100 s
    bucket = TokenBucket(1.0, 10)
    start = bucket.stamp
    assert bucket.take(now=start, n=1000)
    assert not bucket.take(now=start + 100.0)
    assert bucket.take(now=start + 1000.0)
    # a well whose quota is spent is refused before its message is decoded, taking nothing
    reg.quota_spent("E")  # no bucket yet: nothing spent
    reg.quota("E", 10)
    with pytest.raises(InvalidRequest) as info:
        reg.quota_spent("E")
    assert info.value.reason == "well flooding"
    reg.quota_spent("B")  # another well's quota is its own
    owed = TokenBucket(1.0, 10)
    assert owed.take(now=owed.stamp, n=1000)  # 990 tokens owed, repaid at 1 a second
    assert owed.spent(now=owed.stamp + 500.0) and not owed.spent(now=owed.stamp + 992.0)
    assert owed.take(now=owed.stamp + 992.0)  # spent() took nothing


def test_a_flooding_wells_messages_are_refused_before_decoding(tmp_path: Path) -> None:
    """With a quota, a well that spent it is refused at the door: its next message (here
    not even JSON) costs a lookup, not its parsing, and counts as ``well flooding``."""
    from service.engine.fairqueue import FairQueue
    from service.engine.intake import Intake
    from service.inputs import Counters

    settings = loopback_settings(tmp_path, inputs={"well_rate_hz": 1.0, "well_burst": 2})
    counters = Counters()
    intake = Intake(settings, counters, Registry(settings, {}), [FairQueue(100, 100)])
    now = datetime.now(UTC).isoformat()
    sample = {"time": now, "choke": 0.5, "p_up": 80.0, "p_down": 30.0, "t_up": 60.0}
    good = json.dumps({**sample, "eta_gas": 0.2, "eta_oil": 0.5}).encode()
    key = f"{settings.prefix}/F/sensors"
    for _ in range(2):
        intake.deliver(key, good, time.time_ns())
    intake.deliver(key, b"{not json", time.time_ns())
    refused = counters.snapshot()["rejected"]
    assert refused == {"well flooding": 1}, refused  # not "unparseable"
    intake.deliver(f"{settings.prefix}/G/sensors", b"{not json", time.time_ns())
    assert counters.snapshot()["rejected"].get("well flooding") == 1  # G's quota is its own


# -- plausible rates -------------------------------------------------------------------------------
def test_rate_plausibility_relative_to_the_wells_recent_median(tmp_path: Path) -> None:
    settings = loopback_settings(tmp_path, model={"name": "last", "method": "ol"})
    st = WellState("W01", new_learner("W01", settings.model), settings, 0)
    for q in (1000.0, 1100.0, 900.0, 1050.0):
        assert st.rate_problem(q * 100) is None  # too few to judge: only the cap applies
        st.rates.append(q)
    st.rates.append(950.0)
    assert st.rate_problem(1000.0 * 19) is None
    assert st.rate_problem(1000.0 / 19) is None
    for q in (1000.0 * 21, 1000.0 / 21, 0.0, 1e300):
        problem = st.rate_problem(q)
        assert problem is not None and "inputs.rate_factor" in problem
    off = loopback_settings(tmp_path, inputs={"rate_factor": 0})
    st_off = WellState("W02", new_learner("W02", off.model), off, 0)
    st_off.rates.extend([1000.0] * 10)
    assert st_off.rate_problem(0.0) is None


# -- retrain budget and catch-up -------------------------------------------------------------------
def test_live_learners_carry_the_retrain_budget(tmp_path: Path) -> None:
    settings = loopback_settings(tmp_path, model={"retrain_budget_s": 7.5})
    learner = new_learner("W01", settings.model)
    assert learner.train.time_budget_s == 7.5 and learner.method.train.time_budget_s == 7.5
    explicit = loopback_settings(tmp_path, model={"train": {"time_budget_s": 2.0}})
    assert new_learner("W01", explicit.model).train.time_budget_s == 2.0


def test_a_long_gap_runs_one_retrain_not_thousands(tmp_path: Path) -> None:
    settings = loopback_settings(tmp_path, model={"name": "mm", "method": "pbl:1h"})
    learner = new_learner("W01", settings.model)
    x = torch.tensor([list(INPUTS)] * 12, dtype=torch.float64)
    x[:, 0] = torch.linspace(0.3, 0.6, 12)
    y = torch.linspace(900.0, 1300.0, 12, dtype=torch.float64)
    t = torch.tensor([to_ns(T0 + timedelta(minutes=10 * i)) for i in range(12)])
    learner.fit_history(x, y, t)
    due = learner.method.next_due()
    assert due is not None
    learning = Learning(settings, Counters(), None)  # type: ignore[arg-type]
    before = learner.method.n_retrains
    version = learner.version
    later = due + 5 * 3600 * 10**9  # 6 retrains due: fewer than max_catch_up_retrains
    assert not learning.catch_up(learner, later)
    gap = due + 24 * 365 * 3600 * 10**9  # a year later: 8,761 retrains due
    assert learning.catch_up(learner, gap)
    assert learner.method.n_retrains == before + 1 and learner.version == version + 1
    nxt = learner.method.next_due()
    assert nxt is not None and gap < nxt <= gap + 3600 * 10**9
    assert (nxt - due) % (3600 * 10**9) == 0  # the calendar keeps its phase
    started = time.perf_counter()
    learner.predict(list(INPUTS), when=datetime.fromtimestamp(gap / 1e9, UTC))
    assert learner.method.n_retrains == before + 1  # nothing left to catch up
    assert time.perf_counter() - started < 60  # (a hang would hit the test's timeout)


def test_a_hybrid_on_well_tests_catches_up_its_refits_and_one_with_an_mpfm_has_none(
    tmp_path: Path,
) -> None:
    """``bayes`` (``refresh=auto``) on ``ham``: a well whose history is well tests only
    refits every 14 days, and a year's gap collapses into one refit on the calendar's
    phase; a well with an MPFM has no refit to catch up."""
    settings = loopback_settings(tmp_path, model={"name": "ham", "method": "bayes"})
    learning = Learning(settings, Counters(), None)  # type: ignore[arg-type]
    day = 86_400 * 10**9
    x = torch.tensor([list(INPUTS)] * 30, dtype=torch.float64)
    x[:, 0] = torch.linspace(0.3, 0.6, 30)
    y = torch.linspace(900.0, 1300.0, 30, dtype=torch.float64)
    t = torch.tensor([to_ns(T0 + timedelta(days=7 * i)) for i in range(30)])
    for tests_only in (True, False):
        learner = new_learner("W01", settings.model)
        learner.fit_history(x, y, t, well_test=torch.full((30,), tests_only))
        due = learner.method.next_due()
        if not tests_only:
            assert due is None and not learning.catch_up(learner, int(t[-1]) + 365 * day)
            continue
        assert due == int(t[-1]) + 14 * day
        before = learner.method.n_retrains
        gap = due + 365 * day  # 27 refits due
        assert learning.catch_up(learner, gap)
        assert learner.method.n_retrains == before + 1
        nxt = learner.method.next_due()
        assert nxt is not None and gap < nxt <= gap + 14 * day and (nxt - due) % (14 * day) == 0


# -- the engine: new wells off the receiver thread, retiring ----------------------------------------
def test_new_wells_are_built_by_their_worker_and_capped(tmp_path: Path) -> None:
    settings = loopback_settings(
        tmp_path,
        model={"name": "last", "method": "ol"},
        inputs={"max_wells": 3, "new_wells_burst": 100},
    )
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            for w in ("N1", "N2", "N3", "N4"):
                client.send_sample(w, sample_of(T0, INPUTS))
            wait_until(
                lambda: service.counters.snapshot()["rejected"].get("too many wells") == 1,
                10,
                "the refusal",
            )
            engine = service.engine
            assert engine is not None
            wait_until(lambda: len(engine.wells) == 3, 10, "three wells")
            assert set(engine.wells) == {"N1", "N2", "N3"}
            assert set(service.store.wells()) == {"N1", "N2", "N3"}  # type: ignore[union-attr]
            # a retired well stops being served; a purged one frees its id
            result = engine.retire_well("N1")
            assert result["purged"] is False and "N1" not in engine.wells
            assert bus.forgotten == ["N1"]  # the transport let go of its publisher
            assert "N1" not in service.store.wells()  # type: ignore[union-attr]
            client.send_sample("N1", sample_of(T0 + timedelta(minutes=1), INPUTS))
            wait_until(
                lambda: service.counters.snapshot()["rejected"].get("retired well") == 1,
                10,
                "the refusal of a retired well",
            )
            assert service.store.counts()["samples"] == 3  # type: ignore[union-attr]
            engine.retire_well("N2", purge=True)
            assert service.store.history("N2", 0, 2**62, 10) == ([], [])  # type: ignore[union-attr]
            client.send_sample("N2", sample_of(T0 + timedelta(minutes=2), INPUTS))
            wait_until(lambda: "N2" in engine.wells, 10, "N2 created again")
            with pytest.raises(UnknownWell):
                engine.retire_well("N9")
    finally:
        service.stop()
    # after a restart the retired well stays retired, the others come back
    service = Service(settings, MemoryTransport(settings.prefix))
    service.start()
    try:
        assert service.engine is not None
        assert set(service.engine.wells) == {"N2", "N3"}
        assert set(service.engine.retired) == {"N1"}
    finally:
        service.stop()


# -- the store's schema ----------------------------------------------------------------------------
#: the store as the service wrote it before schema 2 (verbatim), to test the migration
_SCHEMA_1 = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE wells (well TEXT PRIMARY KEY, created_ns INTEGER NOT NULL, origin TEXT NOT NULL);
CREATE TABLE samples (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL,
    choke REAL NOT NULL, p_up REAL NOT NULL, p_down REAL NOT NULL, t_up REAL NOT NULL,
    eta_gas REAL NOT NULL, eta_oil REAL NOT NULL,
    received_ns INTEGER NOT NULL,
    q_total REAL, q_gas REAL, q_oil REAL, q_water REAL, version INTEGER
);
CREATE UNIQUE INDEX samples_well_time ON samples (well, time_ns);
CREATE TABLE measurements (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, source TEXT NOT NULL,
    q_total REAL NOT NULL, received_ns INTEGER NOT NULL, via TEXT NOT NULL,
    status TEXT NOT NULL, learn_seq INTEGER, sample_time_ns INTEGER,
    choke REAL, p_up REAL, p_down REAL, t_up REAL, eta_gas REAL, eta_oil REAL,
    predicted REAL, version_after INTEGER
);
CREATE UNIQUE INDEX measurements_key ON measurements (well, source, time_ns);
CREATE INDEX measurements_seq ON measurements (well, learn_seq);
CREATE TABLE checkpoints (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, created_ns INTEGER NOT NULL, version INTEGER NOT NULL,
    learn_seq INTEGER NOT NULL, model TEXT NOT NULL, method TEXT NOT NULL,
    blob BLOB NOT NULL, extra TEXT NOT NULL
);
CREATE INDEX checkpoints_well ON checkpoints (well, id);
CREATE TABLE drift_events (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, statistic REAL, p_value REAL, action TEXT NOT NULL
);
CREATE UNIQUE INDEX drift_events_key ON drift_events (well, time_ns);
INSERT INTO meta VALUES ('schema', '1');
"""


def _schema_1_store(path: Path) -> None:
    con = sqlite3.connect(path)
    con.executescript(_SCHEMA_1)
    t = to_ns(T0)
    con.execute("INSERT INTO wells VALUES ('W01', ?, 'first sight')", (t,))
    con.execute(
        "INSERT INTO samples (well, time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil,"
        " received_ns, q_total, q_gas, q_oil, q_water, version)"
        " VALUES ('W01', ?, 0.4, 120, 30, 60, 0.1, 0.6, ?, 1000, 900, 60, 40, 3)",
        (t, t),
    )
    con.execute(
        "INSERT INTO measurements (well, time_ns, source, q_total, received_ns, via, status,"
        " learn_seq, sample_time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil, predicted,"
        " version_after) VALUES ('W01', ?, 'mpfm', 1020, ?, 'zenoh', 'learned', 1, ?, 0.4, 120,"
        " 30, 60, 0.1, 0.6, 1000, 4)",
        (t, t, t),
    )
    con.commit()
    con.close()


def test_a_schema_1_store_is_migrated_in_place_and_keeps_working(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    _schema_1_store(path)
    store = Store(path)
    try:
        assert store.counts()["samples"] == 1 and store.counts()["measurements"] == 1
        samples, measurements = store.history("W01", 0, 2**62, 10)
        assert samples[0].q_total == 1000 and samples[0].q_total_std is None
        assert measurements[0].status == "learned"
        assert store.wells() == ["W01"] and store.retired_wells() == {}
        assert store.counts()["parameter_history"] == 0  # schema 3's table, empty
        assert store.parameter_history("W01", 0, 2**62, 10) == ([], False)
    finally:
        store.close()
    con = sqlite3.connect(path)
    assert (
        con.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()[0] == SCHEMA_VERSION
    )
    con.close()
    # and a service starts on it: the well is restored from the store and keeps serving
    settings = loopback_settings(
        tmp_path, model={"name": "last", "method": "ol"}, store={"path": str(path)}
    )
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            assert service.engine is not None and "W01" in service.engine.wells
            client.send_measurement(
                "W01", "mpfm", Measurement(time=T0 + timedelta(minutes=1), q_total=1010.0)
            )
            client.send_sample("W01", sample_of(T0 + timedelta(minutes=1), INPUTS))
            # predicted first (by the model re-learned from the old store's measurement) ...
            assert client.wait_for_prediction("W01", T0 + timedelta(minutes=1), 20) == 1020.0
            # ... then it learns the new one
            client.send_sample("W01", sample_of(T0 + timedelta(minutes=2), INPUTS))
            assert client.wait_for_prediction("W01", T0 + timedelta(minutes=2), 20) == 1010.0
    finally:
        service.stop()


def test_a_schema_2_store_gains_the_parameter_history(tmp_path: Path) -> None:
    path = tmp_path / "two.sqlite"
    store = Store(path)
    store.write([AddWell("W01", 1, "history")])
    store.close()
    con = sqlite3.connect(path)  # as the service of schema 2 left it: no parameter_history
    con.execute("DROP TABLE parameter_history")
    con.execute("UPDATE meta SET value = '2' WHERE key = 'schema'")
    con.commit()
    con.close()
    store = Store(path)
    try:
        store.write([InsertParameters("W01", 5, 1, "mm", '{"c_d": {"value": 0.8}}')])
        rows, _ = store.parameter_history("W01", 0, 10, 10)
        assert [(r.time_ns, r.model) for r in rows] == [(5, "mm")]
        assert store.wells() == ["W01"]
    finally:
        store.close()
    con = sqlite3.connect(path)
    assert con.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()[0] == "3"
    indexes = {r[0] for r in con.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
    assert {"parameter_history_time", "parameter_history_id"} <= indexes
    con.close()


def test_a_store_of_a_newer_schema_is_refused_with_a_sentence(tmp_path: Path) -> None:
    path = tmp_path / "new.sqlite"
    Store(path).close()
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value = '99' WHERE key = 'schema'")
    con.commit()
    con.close()
    with pytest.raises(ConfigError, match="schema version 99"):
        Store(path)


def test_every_reason_is_documented() -> None:
    for reason in (
        "time out of range",
        "payload too large",
        "too deeply nested",
        "implausible rate",
        "well flooding",
        "too many wells",
        "too many new wells",
        "retired well",
    ):
        assert reason in REASONS
    page = Path(__file__).parents[1] / "docs" / "guide" / "bad-input.md"
    text = page.read_text(encoding="utf-8")
    missing = [r for r in REASONS if f"`{r}`" not in text]
    assert not missing, f"docs/guide/bad-input.md does not list the reasons {missing}"


def test_refusals_are_counted_per_well_within_a_bound() -> None:
    counters = Counters()
    counters.MAX_WELLS = 2  # type: ignore[misc]
    counters.reject("duplicate", "again", well="W01")
    counters.reject("duplicate", "again", well="W01")
    counters.reject("implausible rate", "far", well="W02")
    counters.reject("implausible rate", "far", well="W03")  # beyond the bound: total only
    counters.reject("unparseable key", "bad")  # no well
    assert counters.rejected_of("W01") == {"duplicate": 2}
    assert counters.rejected_of("W02") == {"implausible rate": 1}
    assert counters.rejected_of("W03") == {}
    assert counters.snapshot()["rejected"] == {
        "duplicate": 2,
        "implausible rate": 2,
        "unparseable key": 1,
    }
    counters.forget("W01")
    assert counters.rejected_of("W01") == {}


class _NoDeclarations:
    """A Zenoh session that refuses to declare publishers or key expressions (each one
    kept declared slows every message the session receives); the rest goes through."""

    def __init__(self, session: object) -> None:
        self._session = session

    def declare_publisher(self, *args: object, **kwargs: object) -> None:
        raise AssertionError("the service declared a publisher")

    def declare_keyexpr(self, *args: object, **kwargs: object) -> None:
        raise AssertionError("the service declared a key expression")

    def __getattr__(self, name: str) -> object:
        return getattr(self._session, name)


def test_predictions_go_out_without_declared_publishers(tmp_path: Path) -> None:
    """Predictions reach another session as JSON with BLOCK, in order, never the service's
    own subscriber, and without a declared publisher or key expression; each well's key is
    parsed once and let go when the well retires."""
    import zenoh

    from replay.client import ZenohBus
    from service.transport import ZenohTransport

    settings = loopback_settings(tmp_path)
    bus = ZenohTransport(settings.zenoh, settings.prefix)
    bus.open()
    delivered: list[str] = []
    try:
        bus._session = _NoDeclarations(bus._session)  # type: ignore[assignment]
        bus.start(lambda key, payload, ns: delivered.append(key))
        endpoint = bus.locators()[0]
        with ZenohBus.connect([endpoint]) as field:
            sub = field.session.declare_subscriber(
                f"{settings.prefix}/**", zenoh.handlers.FifoChannel(1024)
            )
            try:
                got: list[zenoh.Sample] = []
                probe = f"{settings.prefix}/W00/prediction"

                def drain() -> None:
                    while (sample := sub.try_recv()) is not None:
                        got.append(sample)

                deadline = time.monotonic() + 20
                while not got and time.monotonic() < deadline:  # until the subscriber matched
                    bus.publish("W00", b'{"probe": 1}')
                    time.sleep(0.05)
                    drain()
                assert got, "no prediction reached the other session"
                bus.publish("W01", b'{"n": 1}')
                bus.publish("W02", b'{"n": 2}')
                deadline = time.monotonic() + 20
                while time.monotonic() < deadline:
                    drain()
                    if sum(str(g.key_expr) != probe for g in got) >= 2:
                        break
                    time.sleep(0.01)
            finally:
                sub.undeclare()
        ours = [g for g in got if str(g.key_expr) != probe]
        assert [(str(g.key_expr), g.payload.to_bytes()) for g in ours] == [
            (f"{settings.prefix}/W01/prediction", b'{"n": 1}'),
            (f"{settings.prefix}/W02/prediction", b'{"n": 2}'),
        ]
        for g in got:
            assert str(g.encoding) == "application/json"
            assert g.congestion_control == zenoh.CongestionControl.BLOCK
        assert not [k for k in delivered if k.endswith("/prediction")]  # never back to itself
        assert set(bus._keys) == {"W00", "W01", "W02"}
        bus.forget("W01")
        bus.forget("W09")  # never published: nothing to do
        assert set(bus._keys) == {"W00", "W02"}
        bus.publish("W01", b"{}")  # a well that returns is published again
        assert set(bus._keys) == {"W00", "W01", "W02"}
    finally:
        bus.close()
