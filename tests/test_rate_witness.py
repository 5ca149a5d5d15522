"""The choke-rate witness: a move of the choke's reading that the measured rate does not
follow is a choke offset (vfm_core.rate_witness)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vfm_core.errors import ConfigError
from vfm_core.rate_witness import MIN_READINGS, ChokeRateWitness

DAY = 86_400 * 10**9
HALF_DAY = DAY // 2
ELASTICITY = 0.9
SHARE = 0.1 / 22  # the detectors' budget per test (vfm_core.sensor_faults)


def _well(days: int, seed: int, *, noise: float = 0.02, offset: tuple[int, float] | None = None):
    """A synthetic well sampled twice a day: the operator moves the choke every 6-14 days
    by 2-8 % (either way); the rate is u**0.9 times 2 % meter noise. ``offset`` = (day,
    relative size): from that day the reading is the true opening times (1 + size), while
    the rate keeps following the true opening. Returns (times ns, readings, rates)."""
    rng = np.random.default_rng(seed)
    u, next_move = 0.4, 10
    times, readings, rates = [], [], []
    for k in range(days * 2):
        day = k // 2
        if day == next_move and k % 2 == 0:
            u = float(np.clip(u * (1 + rng.choice([-1, 1]) * rng.uniform(0.02, 0.08)), 0.1, 0.9))
            next_move = day + int(rng.integers(6, 15))
        read = u if offset is None or day < offset[0] else u * (1 + offset[1])
        times.append(1_500_000_000 * 10**9 + k * HALF_DAY)
        readings.append(read)
        rates.append(100.0 * u**ELASTICITY * (1 + noise * rng.standard_normal()))
    return times, readings, rates


def _run(times, readings, rates, witness=None, start=0):
    w = witness or ChokeRateWitness(SHARE)
    found = []
    for t, u, q in zip(times[start:], readings[start:], rates[start:], strict=True):
        w.choke(t, u)
        f = w.rate(t, q)
        if f is not None:
            found.append(f)
    return w, found


def test_a_reading_that_steps_without_the_rate_is_found_at_its_start():
    times, readings, rates = _well(500, 1, offset=(400, 0.15))
    w, found = _run(times, readings, rates)
    raised = [f for f in found if f.action == "raise"]
    assert len(raised) == 1
    step = times[400 * 2]
    assert raised[0].start_ns == step
    assert raised[0].time_ns - step <= 7 * DAY
    assert "did not follow" in raised[0].evidence and "elasticity" in raised[0].evidence


def test_the_well_elasticity_is_learned_from_its_moves():
    times, readings, rates = _well(400, 2)
    w, found = _run(times, readings, rates)
    assert found == []
    beta, s, omega, kappa, se_beta = w.fit()
    assert abs(beta - ELASTICITY) < 3 * se_beta + 0.05
    assert abs(beta - ELASTICITY) < abs(0.0 - ELASTICITY) / 5  # far nearer the truth than none
    assert 0.01 < s < 0.03  # the readings' own noise (2 %)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_a_clean_well_raises_nothing(seed):
    times, readings, rates = _well(1100, seed)
    _, found = _run(times, readings, rates)
    assert found == []


def test_a_rate_that_fell_for_another_reason_is_not_a_choke_offset():
    """At a small move the rate drops by 8 % (something else changed): short of the
    response, but not the 'nothing happened' a reading-only move leaves."""
    times, readings, rates = _well(500, 6)
    moves = [i for i in range(1, len(readings)) if readings[i] != readings[i - 1]]
    at = next(i for i in moves if i > 600)
    rates = [q * (0.92 if i >= at else 1.0) for i, q in enumerate(rates)]
    _, found = _run(times, readings, rates)
    assert [f for f in found if f.action == "raise" and f.start_ns == times[at]] == []


def test_the_reading_coming_back_closes_the_offset():
    """The operator stops moving the choke from day 390 to 470; the reading steps +15 % on
    day 400 and comes back on day 430, the rate following neither."""
    times, readings, rates = _well(390, 7)
    u = readings[-1]
    rng = np.random.default_rng(70)
    for k in range(390 * 2, 480 * 2):
        day = k // 2
        times.append(times[0] + k * HALF_DAY)
        readings.append(u * 1.15 if 400 <= day < 430 else u)
        rates.append(100.0 * u**ELASTICITY * (1 + 0.02 * rng.standard_normal()))
    _, found = _run(times, readings, rates)
    assert [f.action for f in found] == ["raise", "close"]
    assert found[0].start_ns == times[400 * 2]
    assert found[1].start_ns == times[430 * 2]
    assert "right again" in found[1].evidence


def test_the_state_resumes_to_the_same_findings():
    times, readings, rates = _well(500, 8, offset=(400, 0.15))
    whole, found = _run(times, readings, rates)
    first, _ = _run(times[:700], readings[:700], rates[:700])
    again = ChokeRateWitness(SHARE)
    again.restore(json.loads(json.dumps(first.state())))
    _, rest = _run(times, readings, rates, witness=again, start=700)
    assert [(f.action, f.start_ns, f.time_ns) for f in rest] == [
        (f.action, f.start_ns, f.time_ns) for f in found
    ]


def test_too_few_moves_or_bad_readings_say_nothing():
    w = ChokeRateWitness(SHARE)
    assert w.fit() is None
    w.choke(0, 0.4)
    assert w.rate(0, float("nan")) is None
    assert w.rate(1, -5.0) is None
    assert w.rate(2, 0.0) is None
    assert len(w.readings) == 0
    w.choke(3, 0.5)
    assert w.rate(4, 10.0) is None  # no elasticity yet
    assert math.isclose(w.moves_per_year(), 12.0)


def test_a_shut_in_or_gap_breaks_the_windows():
    w = ChokeRateWitness(SHARE)
    w.choke(0, 0.4)
    w.rate(0, 10.0)
    w.choke(DAY, 0.0)  # shut in
    assert w.u is None and w.closed_segment == w.segment
    w.choke(2 * DAY, 0.5)  # reopened: a new level, no move across the shut-in
    assert not w.pending
    w.choke(10 * DAY, 0.55)  # after a gap of eight days
    assert not w.pending and w.closed_segment == w.segment


def test_a_choke_offset_holds_learning_and_stands_in_with_where_the_rate_says_it_is():
    """Through the well's detectors (vfm_core.sensor_faults): once the witness raises the
    offset, measurements paired with samples since the step are held, and the choke's
    stand-in is the reading less the estimated shift: near the true opening (its 90 % span
    holding it), also after the operator moves the choke during the offset."""
    from vfm_core.sensor_faults import WellSensorFaults

    times, readings, rates = _well(428, 1, offset=(400, 0.15))
    truth = [r / 1.15 if k >= 800 else r for k, r in enumerate(readings)]
    rng = np.random.default_rng(90)
    det = WellSensorFaults()
    raised_at = None
    doubted = []
    for k, (t, u, q) in enumerate(zip(times, readings, rates, strict=True)):
        x = [u, *(v * (1 + 0.003 * rng.standard_normal()) for v in (120, 30, 60, 0.1, 0.6))]
        det.update(t, x)
        events = det.measure(t, q, x)
        if raised_at is None and any(e.sensor == "choke" for e in events):
            raised_at = k
        if raised_at is None and det.suspect(t) is not None:
            doubted.append(k)  # held before the offset is decided: the witness in doubt
    assert raised_at is not None and raised_at - 800 <= 14  # within 7 days of the step
    # from the first reading after the step on, nothing is learned (the witness in doubt,
    # then the offset found); before it, only a few readings right after real moves
    assert set(range(800, raised_at)) <= set(doubted)
    assert len([k for k in doubted if k < 800]) < 0.05 * 800
    assert det.suspect(times[799]) is None  # before the step: learned
    fault = det.suspect(times[810])
    assert fault is not None and (fault.sensor, fault.kind) == ("choke", "offset")
    assert det.stands_in()
    for k in (raised_at, len(times) - 1):  # at detection, and after later moves
        (fb,) = det.fallbacks(times[k], [readings[k], 120, 30, 60, 0.1, 0.6])
        assert (fb.sensor, fb.kind, fb.measured) == ("choke", "offset", readings[k])
        assert abs(fb.value - truth[k]) < 0.25 * (readings[k] - truth[k])
        assert fb.low <= truth[k] <= fb.high < readings[k]
    assert readings[-1] != readings[raised_at]  # the operator did move it meanwhile


@pytest.mark.parametrize("fixed", [True, False])
def test_a_choke_offset_closes_across_a_shut_in_only_when_the_reading_came_back(fixed):
    """A 15 % offset found on day 400; the well is shut in on days 410-412 and reopens at
    the same true opening: with the transmitter set right meanwhile (the reading back at
    the truth) the offset closes once the reopened level has its readings (the rate level
    matches the reading, not the reading less the shift), otherwise it stays open and
    stood in for."""
    from vfm_core.sensor_faults import WellSensorFaults

    times, readings, rates = _well(430, 1, offset=(400, 0.15))
    rng = np.random.default_rng(91)
    u_true = readings[819] / 1.15  # the opening since the move of day 405
    for k in range(820, 860):  # no operator move: the offset is the only change
        shut = k < 826
        readings[k] = 0.0 if shut else (u_true if fixed else u_true * 1.15)
        rates[k] = (
            float("nan")
            if shut
            else 100.0 * u_true**ELASTICITY * (1 + 0.02 * rng.standard_normal())
        )
    det = WellSensorFaults()
    closed_at = None
    for k, (t, u, q) in enumerate(zip(times[:860], readings[:860], rates[:860], strict=True)):
        x = [u, *(v * (1 + 0.003 * rng.standard_normal()) for v in (120, 30, 60, 0.1, 0.6))]
        for e in det.update(t, x) + (det.measure(t, q, x) if math.isfinite(q) else []):
            if e.sensor == "choke" and e.end_ns is not None:
                closed_at = k
    if fixed:
        assert closed_at == 826 + MIN_READINGS - 1  # once the new level has its readings
        assert ("choke", "offset") not in det.open and not det.stands_in()
        (choke,) = [e for e in det.events if e.sensor == "choke"]
        assert "right again" in choke.evidence
    else:
        assert closed_at is None and ("choke", "offset") in det.open
        (fb,) = det.fallbacks(times[859], [readings[859], 120, 30, 60, 0.1, 0.6])
        assert abs(fb.value - u_true) < 0.25 * (readings[859] - u_true)


def test_an_offset_taken_as_real_ends_without_a_new_one():
    """The operator stops moving the choke from day 390 to 600; the reading is 15 % high
    from day 400 to 590, the rate following neither step: the offset is found, taken as
    real after 180 days (the model learns again), and the reading coming back on day 590
    is that offset's end, not a new offset."""
    from vfm_core.sensor_faults import WellSensorFaults

    times, readings, rates = _well(390, 7)
    u = readings[-1]
    rng = np.random.default_rng(71)
    for k in range(390 * 2, 600 * 2):
        times.append(times[0] + k * HALF_DAY)
        readings.append(u * 1.15 if 400 <= k // 2 < 590 else u)
        rates.append(100.0 * u**ELASTICITY * (1 + 0.02 * rng.standard_normal()))
    det = WellSensorFaults()
    events = []
    for t, r, q in zip(times, readings, rates, strict=True):
        x = [r, *(v * (1 + 0.003 * rng.standard_normal()) for v in (120, 30, 60, 0.1, 0.6))]
        events += [(e.kind, e.end_ns) for e in det.update(t, x) + det.measure(t, q, x)]
    # (half a year without a move also reads as a frozen choke: not the point here)
    chokes = [e for e in det.events if (e.sensor, e.kind) == ("choke", "offset")]
    assert len(chokes) == 1, [(e.start_ns, e.end_ns, e.evidence[-120:]) for e in chokes]
    found = chokes[0]
    assert found.start_ns == times[800] and found.end_ns is not None
    assert 180 <= (found.end_ns - found.detected_ns) / DAY < 181  # accepted before day 590
    assert "taken as the choke's" in found.evidence
    assert det.witness.accepted is None  # the move back was its end
    assert not det.stands_in()


def test_a_restart_during_a_choke_offset_resumes_its_stand_in_and_its_end():
    """The detectors' state saved while a choke offset is open (a restart of the service)
    resumes it: the same stand-in at every later sample, and the same end as without the
    restart when the transmitter is set right during a shut-in (days 410-412; only the rate
    level after it can tell, from what the witness kept of the offset)."""
    from vfm_core.sensor_faults import WellSensorFaults

    times, readings, rates = _well(390, 7)
    u = readings[-1]
    rng = np.random.default_rng(72)
    for k in range(390 * 2, 440 * 2):
        times.append(times[0] + k * HALF_DAY)
        shut = 820 <= k < 826
        readings.append(0.0 if shut else u * 1.15 if 400 <= k // 2 < 410 else u)
        rates.append(
            math.nan if shut else 100.0 * u**ELASTICITY * (1 + 0.02 * rng.standard_normal())
        )
    rows = [
        [r, *(v * (1 + 0.003 * rng.standard_normal()) for v in (120, 30, 60, 0.1, 0.6))]
        for r in readings
    ]

    def run(det, ks):
        seen = []
        for k in ks:
            det.update(times[k], rows[k])
            measured = det.measure(times[k], rates[k], rows[k]) if math.isfinite(rates[k]) else []
            ended = [e.end_ns for e in measured]
            stood = [round(f.value, 12) for f in det.fallbacks(times[k], rows[k])]
            seen.append((k, ended, stood))
        return seen

    whole = WellSensorFaults()
    expected = run(whole, range(len(times)))
    first = WellSensorFaults()
    run(first, range(815))  # the offset found (day ~400), open before the shut-in
    assert ("choke", "offset") in first.open
    again = WellSensorFaults()
    assert again.restore(json.loads(json.dumps(first.state())))
    assert run(again, range(815, len(times))) == expected[815:]
    assert any(ended for _, ended, _ in expected[826:832])  # ended after the reopening
    assert any(stood for _, _, stood in expected[815:820])  # and stood in before that


@pytest.mark.parametrize("share,window", [(0.0, 7.0), (float("nan"), 7.0), (0.01, 0.5)])
def test_bad_settings_are_refused(share, window):
    with pytest.raises(ConfigError):
        ChokeRateWitness(share, window)


# -- through the service ----------------------------------------------------------------------


def test_the_service_shows_a_choke_offset_its_mpfm_reveals(tmp_path):
    """Samples and MPFM readings twice a day for 420 days over the bus; from day 400 the
    choke's reading is 15 % above the true opening, the rate following the truth:
    ``GET /wells/W01`` lists a choke offset that began at the step, open, and ``/metrics``
    has it; the MPFM readings after it was found are held (not learned), and the latest
    prediction stood in for the choke with about the true opening."""
    import asyncio
    from datetime import UTC, datetime

    import httpx

    from replay.client import FieldClient, sample_of
    from service.app import Service
    from service.http import create_app
    from service.testing import loopback_settings, wait_until
    from service.transport import MemoryTransport
    from vfm_core.messages import Measurement
    from vfm_core.timeutil import iso

    times, readings, rates = _well(420, 1, offset=(400, 0.15))
    settings = loopback_settings(tmp_path, model={"name": "mm", "method": "pbl:3650d"})
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            for t, u, q in zip(times, readings, rates, strict=True):
                when = datetime.fromtimestamp(t / 1e9, tz=UTC)
                client.send_sample("W01", sample_of(when, (u, 120.0, 30.0, 60.0, 0.1, 0.6)))
                client.send_measurement("W01", "mpfm", Measurement(time=when, q_total=q))
            engine = service.engine
            assert engine is not None
            store = service.store
            assert store is not None
            wait_until(
                lambda: (
                    engine.has_well("W01")
                    and len(store.history("W01", 0, 2**62, 10_000)[1]) == len(times)
                    and all(
                        m.status != "pending" for m in store.history("W01", 0, 2**62, 10_000)[1]
                    )
                ),
                120,
                "every measurement to be settled",
            )

            async def get(path: str) -> httpx.Response:
                transport = httpx.ASGITransport(app=create_app(service))
                async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
                    return await c.get(path)

            body = asyncio.run(get("/wells/W01")).json()
            faults = body["sensor_faults"]
            (stood,) = body["fallback"]
            assert (stood["sensor"], stood["kind"], stood["measured"]) == (
                "choke",
                "offset",
                readings[-1],
            )
            true_u = readings[-1] / 1.15
            assert abs(stood["value"] - true_u) < 0.25 * (readings[-1] - true_u)
            statuses = [m.status for m in store.history("W01", 0, 2**62, 10_000)[1]]
            # before the step, only readings right after a move whose rate had not (yet)
            # followed it, the witness in doubt: a few
            assert set(statuses[:800]) <= {"learned", "held"}
            assert statuses[:800].count("held") < 0.05 * 800
            assert statuses[-20:] == ["held"] * 20  # after it was found: not learned
            chokes = [f for f in faults if f["sensor"] == "choke"]
            assert [(f["kind"], f["end"]) for f in chokes] == [("offset", None)]
            assert chokes[0]["start"] == iso(times[800])
            assert "did not follow" in chokes[0]["evidence"]
            metrics = asyncio.run(get("/metrics")).text
            assert (
                'vfm_well_sensor_fault_active{kind="offset",sensor="choke",well="W01"} 1.0'
                in metrics
            )
    finally:
        service.stop()


def _sand_then_closed_in(seed: int, *, choke_moves: bool):
    """300 days of :func:`_well`, then the choke still for 20 days, a step of the rate by
    +10 % with the choke still (a sand event that raised C_D), and two days later the
    operator's corrective move that closes the choke by the elasticity's share of it (the
    rate back at its old level). ``choke_moves`` False: only the reading moves (a real
    offset after the same step; the rate stays up)."""
    times, readings, rates = _well(300, seed)
    rng = np.random.default_rng(seed + 1000)
    u0 = readings[-1]
    u1 = u0 * 1.1 ** (-1.0 / ELASTICITY)
    for k in range(80):  # 40 more days, twice a day
        stepped, moved = k >= 40, k >= 44
        u = u1 if (moved and choke_moves) else u0
        times.append(times[-1] + HALF_DAY)
        readings.append(u1 if moved else u0)
        rates.append(100.0 * u**ELASTICITY * (1.1 if stepped else 1.0)
                     * (1 + 0.02 * rng.standard_normal()))  # fmt: skip
    return times, readings, rates, times[600 + 44]


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_a_rate_step_before_the_operators_corrective_move_is_no_choke_offset(seed):
    """Strong erosion: C_D steps up with the choke still, the operator closes in two days
    later and the rate comes back to its old level. Over the whole week before the move the
    rate's mean lies between its two levels, so the move's response looked short (an
    offset raised on the lead's code); taken from the rate's latest level it is what the
    elasticity says. The same step followed by a move of the reading alone is still one."""
    times, readings, rates, move = _sand_then_closed_in(seed, choke_moves=True)
    _, found = _run(times, readings, rates)
    assert [f for f in found if f.start_ns == move] == []
    times, readings, rates, move = _sand_then_closed_in(seed, choke_moves=False)
    _, found = _run(times, readings, rates)
    raised = [f for f in found if f.action == "raise" and f.start_ns == move]
    assert len(raised) == 1 and "the rate's level since" in raised[0].evidence
