"""Well-test QC in the service: a well test far off the model and off the MPFM is held for
review (status ``review``), flagged in GET /wells/{well}, counted, and not learned until the
operator accepts it over HTTP with the token; rejected, it is never learned.

The model is ``last`` (the latest learned rate) with ``ol``, so what was learned shows in
the next prediction and in the version; it has no interval, so the spread is the robust
one of the well's own residuals (service.engine.alarms.WellTestReview). The field: one MPFM
reading a day around 1000 Sm3/h with 2 % noise (seeded), so the residuals' spread is about
3 % and a well test 30 % off lies near |z| = 12.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import httpx
import numpy as np
import pytest

from replay.client import FieldClient, sample_of
from service.app import Service
from service.config import load_settings
from service.engine import Engine
from service.engine.alarms import MpfmCheck, WellTestReview, _t_threshold
from service.engine.state import WellState
from service.http import create_app
from service.store import Store
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement
from vfm_core.timeutil import iso, to_ns

pytestmark = pytest.mark.timeout(120)

T0 = datetime(2022, 2, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -
TOKEN = "well-test-review-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
DAYS = 20


@dataclass
class Rig:
    service: Service
    client: FieldClient

    @property
    def engine(self) -> Engine:
        assert self.service.engine is not None
        return self.service.engine

    @property
    def store(self) -> Store:
        assert self.service.store is not None
        return self.service.store

    def statuses(self) -> dict[tuple[str, int], str]:
        return {
            (m.source, m.time_ns): m.status for m in self.store.history("W01", 0, 2**62, 10**4)[1]
        }

    def http(self, method: str, path: str, **kw: Any) -> httpx.Response:
        app = create_app(self.service)

        async def go() -> httpx.Response:
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
                return await client.request(method, path, **kw)

        return asyncio.run(go())

    def version(self) -> int:
        return int(self.engine.well_view("W01")["version"])

    def predict_at(self, when: datetime) -> float:
        self.client.send_sample("W01", sample_of(when, INPUTS))
        return self.client.wait_for_prediction("W01", when)


@contextmanager
def rig(folder: Path, **overrides: Any) -> Iterator[Rig]:
    settings = loopback_settings(
        folder, model={"name": "last", "method": "ol"}, http={"token": TOKEN}, **overrides
    )
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            yield Rig(service, client)
    finally:
        service.stop()


def send_field(r: Rig, seed: int) -> datetime:
    """DAYS daily MPFM readings around 1000 Sm3/h (2 % noise), each with its sample; all
    learned. Returns the time of the last one."""
    rng = np.random.default_rng(seed)
    times = [T0 + timedelta(days=i) for i in range(DAYS)]
    for t in times:
        r.client.send_sample("W01", sample_of(t, INPUTS))
        q = 1000.0 * math.exp(0.02 * float(rng.standard_normal()))
        r.client.send_measurement("W01", "mpfm", Measurement(time=t, q_total=q))
    wait_until(
        lambda: sum(s == "learned" for s in r.statuses().values()) == DAYS, 30, "the readings"
    )
    return times[-1]


def post_well_test(
    r: Rig, when: datetime, q: float, headers: dict[str, str] = AUTH
) -> httpx.Response:
    return r.http(
        "POST",
        "/wells/W01/well-tests",
        json={"time": iso(to_ns(when)), "q_total": q},
        headers=headers,
    )


def decide(r: Rig, when: datetime, decision: str, headers: dict[str, str] = AUTH) -> httpx.Response:
    body = {"time": iso(to_ns(when)), "source": "well_test", "decision": decision}
    return r.http("POST", "/wells/W01/measurements/review", json=body, headers=headers)


def test_a_bad_well_test_is_held_flagged_counted_not_learned_then_accepted(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        last = send_field(r, seed=11)
        level = r.predict_at(last + timedelta(hours=1))  # the last reading (model `last`)
        # two days after the last MPFM reading: no MPFM within 24 h of the well test
        when = last + timedelta(days=2)
        r.client.send_sample("W01", sample_of(when, INPUTS))
        r.client.wait_for_prediction("W01", when)
        version = r.version()
        answer = post_well_test(r, when, 0.7 * level)
        assert answer.status_code == 202, answer.text
        body = answer.json()
        assert body["status"] == "review" and not body["model_changed"]
        assert "held for review" in body["message"] and "30 % below" in body["message"]
        assert "no MPFM reading" in body["message"]
        # stored with status review; flagged; counted; not learned
        assert r.statuses()[("well_test", to_ns(when))] == "review"
        view = r.http("GET", "/wells/W01").json()
        (held,) = view["held_for_review"]
        assert set(held) == {"time", "source", "q_total", "predicted", "z", "mpfm", "reason"}
        assert held["time"] == iso(to_ns(when)) and held["source"] == "well_test"
        assert held["q_total"] == pytest.approx(0.7 * level)
        assert held["predicted"] == pytest.approx(level)
        assert held["z"] < -_t_threshold(3.29, DAYS - 1) and held["mpfm"] is None
        assert view["rejected"] == {"held for review": 1}
        assert view["version"] == version
        metrics = r.http("GET", "/metrics").text
        assert 'vfm_inputs_rejected_total{reason="held for review"} 1.0' in metrics
        assert 'vfm_well_held_for_review{well="W01"} 1.0' in metrics
        later = when + timedelta(hours=1)
        assert r.predict_at(later) == pytest.approx(level)  # the model did not learn it

        # the operator accepts it: learned now, paired with its stored sample
        assert decide(r, when, "accept", headers={}).status_code == 401
        assert (
            decide(r, when, "accept", headers={"Authorization": "Bearer wrong"}).status_code == 401
        )
        ok = decide(r, when, "accept")
        assert ok.status_code == 200, ok.text
        assert ok.json()["status"] == "learned" and ok.json()["model_changed"]
        assert ok.json()["paired_sample_time"] == iso(to_ns(when))
        assert r.version() == version + 1
        assert r.predict_at(later + timedelta(hours=1)) == pytest.approx(0.7 * level)
        assert r.statuses()[("well_test", to_ns(when))] == "learned"
        view = r.http("GET", "/wells/W01").json()
        assert view["held_for_review"] == []
        assert 'vfm_well_held_for_review{well="W01"} 0.0' in r.http("GET", "/metrics").text
        (row,) = r.store.reviews("W01", "well_test", to_ns(when))
        assert row.decision == "accept" and row.decided_ns is not None
        # a decision is final; an unknown measurement is not held
        again = decide(r, when, "reject")
        assert again.status_code == 409 and again.json()["reason"] == "no such review"
        none = decide(r, when - timedelta(days=1), "accept")
        assert none.status_code == 422 and "held_for_review" in none.json()["detail"]
        assert r.service.counters.snapshot()["events"]["reviews accepted"] == 1


def test_a_rejected_well_test_is_never_learned_and_a_good_one_is(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        last = send_field(r, seed=12)
        level = r.predict_at(last + timedelta(hours=1))
        # in distribution (1 % off): learned as before
        good = last + timedelta(days=2)
        r.client.send_sample("W01", sample_of(good, INPUTS))
        r.client.wait_for_prediction("W01", good)
        version = r.version()
        answer = post_well_test(r, good, 1.01 * level)
        assert answer.status_code == 200 and answer.json()["status"] == "learned", answer.text
        assert r.version() == version + 1
        # 30 % above, over Zenoh this time: held, then rejected
        bad = last + timedelta(days=4)
        r.client.send_sample("W01", sample_of(bad, INPUTS))
        r.client.wait_for_prediction("W01", bad)
        r.client.send_measurement("W01", "well_test", Measurement(time=bad, q_total=1.3 * level))
        wait_until(lambda: r.statuses().get(("well_test", to_ns(bad))) == "review", 10, "held")
        version = r.version()
        bad_body = {"time": iso(to_ns(bad)), "source": "well_test", "decision": "maybe"}
        refused = r.http("POST", "/wells/W01/measurements/review", json=bad_body, headers=AUTH)
        assert refused.status_code == 422 and refused.json()["detail"]
        no = decide(r, bad, "reject")
        assert no.status_code == 202 and no.json()["status"] == "rejected", no.text
        assert r.statuses()[("well_test", to_ns(bad))] == "rejected"
        assert r.version() == version
        assert r.predict_at(bad + timedelta(hours=1)) == pytest.approx(1.01 * level)
        assert r.http("GET", "/wells/W01").json()["held_for_review"] == []
        assert r.service.counters.snapshot()["events"]["reviews rejected"] == 1


def test_a_well_test_the_mpfm_confirms_is_learned(tmp_path: Path) -> None:
    """30 % off the model, but the MPFM reads the same within the window: the well changed."""
    with rig(tmp_path) as r:
        last = send_field(r, seed=13)
        level = r.predict_at(last + timedelta(hours=1))
        when = last + timedelta(days=2)
        r.client.send_sample("W01", sample_of(when, INPUTS))
        r.client.wait_for_prediction("W01", when)
        # an MPFM reading an hour later, stored but waiting for its sample (not learned yet)
        mpfm_at = when + timedelta(hours=1)
        r.client.send_measurement("W01", "mpfm", Measurement(time=mpfm_at, q_total=0.71 * level))
        wait_until(lambda: ("mpfm", to_ns(mpfm_at)) in r.statuses(), 10, "the MPFM reading")
        version = r.version()
        answer = post_well_test(r, when, 0.7 * level)
        assert answer.status_code == 200 and answer.json()["status"] == "learned", answer.text
        assert r.version() == version + 1
        assert r.http("GET", "/wells/W01").json()["held_for_review"] == []


def test_a_second_well_test_like_the_held_one_is_learned(tmp_path: Path) -> None:
    """Two well tests in a row off the model and alike: the well changed. The second is
    learned (the model catches up), the first stays held for the operator; a third far
    from both is held again."""
    with rig(tmp_path) as r:
        last = send_field(r, seed=16)
        level = r.predict_at(last + timedelta(hours=1))
        first, second, third = (last + timedelta(days=d) for d in (2, 4, 6))
        for when in (first, second, third):
            r.client.send_sample("W01", sample_of(when, INPUTS))
            r.client.wait_for_prediction("W01", when)
        version = r.version()
        assert post_well_test(r, first, 0.7 * level).json()["status"] == "review"
        answer = post_well_test(r, second, 0.69 * level)
        assert answer.status_code == 200 and answer.json()["status"] == "learned", answer.text
        assert r.version() == version + 1
        (held,) = r.http("GET", "/wells/W01").json()["held_for_review"]
        assert held["time"] == iso(to_ns(first))
        # the model now says 0.69 * level; a well test at 1.3 * level is far from it and
        # from the held one
        assert post_well_test(r, third, 1.3 * level).json()["status"] == "review"
        assert len(r.http("GET", "/wells/W01").json()["held_for_review"]) == 2


def test_held_well_tests_survive_a_restart(tmp_path: Path) -> None:
    with rig(tmp_path) as r:
        last = send_field(r, seed=14)
        level = r.predict_at(last + timedelta(hours=1))
        when = last + timedelta(days=3)
        r.client.send_sample("W01", sample_of(when, INPUTS))
        r.client.wait_for_prediction("W01", when)
        assert post_well_test(r, when, 0.6 * level).json()["status"] == "review"
    with rig(tmp_path) as r:
        (held,) = r.http("GET", "/wells/W01").json()["held_for_review"]
        assert held["time"] == iso(to_ns(when))
        assert decide(r, when, "reject").json()["status"] == "rejected"


def test_disabled_learns_every_well_test(tmp_path: Path) -> None:
    with rig(tmp_path, well_test_review={"enabled": False}) as r:
        last = send_field(r, seed=15)
        level = r.predict_at(last + timedelta(hours=1))
        when = last + timedelta(days=2)
        r.client.send_sample("W01", sample_of(when, INPUTS))
        r.client.wait_for_prediction("W01", when)
        assert post_well_test(r, when, 0.7 * level).json()["status"] == "learned"


def test_the_interval_sets_the_spread_and_residuals_the_rest(tmp_path: Path) -> None:
    """A method with an interval: the sd is its 90 % interval's, in log space; without one,
    the MAD of the residuals, with Student's t threshold for their number; with both, the
    one that allows more."""
    settings = load_settings(None, store={"path": str(tmp_path / "s.sqlite")})
    review = WellTestReview(settings, MpfmCheck(settings, Store(tmp_path / "s.sqlite")))
    residuals = [0.03, -0.03, 0.01, -0.01, 0.02, -0.02, 0.0, 0.05, -0.05, 0.03]

    def spread(n: int, rates: dict[str, float | None]) -> tuple[float, float] | None:
        st = cast(WellState, SimpleNamespace(log_residuals=residuals[:n]))
        return review.spread(st, rates)

    assert spread(10, {"q_total_p05": 900.0, "q_total_p95": 1100.0}) == (
        pytest.approx(math.log(1100 / 900) / (2 * 1.6448536)),
        3.29,
    )
    found = spread(10, {})
    assert found is not None
    assert found[0] == pytest.approx(1.4826 * 0.025)
    assert found[1] == pytest.approx(_t_threshold(3.29, 10)) and found[1] > 3.29
    # an interval narrower than the errors the model shows: the residuals' spread rules
    assert spread(10, {"q_total_p05": 990.0, "q_total_p95": 1010.0}) == found
    assert spread(5, {}) is None  # too few residuals and no interval: nothing is held
    # the interval alone, its sd (0.6 %) raised to the floor well_test_review.min_sd (1 %)
    assert math.log(1010 / 990) / (2 * 1.6448536) < 0.01
    assert spread(5, {"q_total_p05": 990.0, "q_total_p95": 1010.0}) == (0.01, 3.29)
