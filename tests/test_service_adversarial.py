"""An adversarial suite against a real ``vfm serve`` process, over Zenoh and HTTP.

Every case is tallied as one of:

* **answered**: the service counted it under a rejection reason (or accepted it, where
  that is right), or answered over HTTP with a documented status and ``{detail, reason}``;
* **crashed**: no answer (nothing counted, the worker stopped answering, the process
  died), an HTTP 500 or an undocumented answer, or an internal error counted;
* **lost**: a measurement or well test the service acknowledged (an HTTP 200/202, or a
  prediction published for a later sample of its well, which happens only after the
  commit) missing from the store after a ``kill -9`` and a restart.

What runs: a corpus of bad inputs over Zenoh (times outside the representable span and
before 1970, JSON nested 50,000 deep and 20 MB payloads, well ids with newlines, NUL,
control characters, ``..`` and 10 kB, rates of 1e300, zero and 30 times the well's median,
samples from the future, integers of 400 digits, ...); the same and more over HTTP (bodies
past the limit, bad query bounds, method specs such as ``pbl:1ns`` and ``pbl:auto``,
typos of well names, retiring wells); floods bounded in time (one well as fast as Zenoh
takes it while another well keeps sending, thousands of new well names, concurrent HTTP
posts); and ``kill -9`` at several moments: while a field streams, during a model change,
during a flood, right after acknowledged well tests; and a SIGTERM during a model change
(a clean stop, exit status 0).

The figures are printed at the end (``pytest -s``) and written to the JSON file named by
``VFM_ADVERSARIAL_REPORT`` if it is set; the last test asserts that nothing crashed and
nothing was lost. No timing is asserted (shared machines are noisy): floods are bounded
by the test's own clock, and the good well's latency during the flood is only reported.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest
import zenoh

from replay.client import FieldClient, ZenohBus, sample_of
from service.testing import ServeProcess, wait_until
from vfm_core.messages import Measurement
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field
from vfm_core.timeutil import to_ns

pytestmark = pytest.mark.timeout(600)

SPLIT = "2016-04-01"
TOKEN = "adversarial-test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SENTINEL = "W02"  # has a history: answers every sample; bad inputs go to it or to new wells
STREAMED = ("W01", "W03")  # streamed, killed, model-changed
DOCUMENTED = {200, 202, 401, 403, 404, 405, 409, 413, 422, 503}


# -- the tally ---------------------------------------------------------------------------------
@dataclass
class Case:
    name: str
    channel: str  # zenoh | http | flood | kill
    outcome: str  # answered | crashed | lost
    detail: str = ""


@dataclass
class Tally:
    cases: list[Case] = field(default_factory=list)
    acknowledged: int = 0
    lost: int = 0
    notes: dict[str, Any] = field(default_factory=dict)

    def add(self, name: str, channel: str, ok: bool, detail: str = "") -> None:
        self.cases.append(Case(name, channel, "answered" if ok else "crashed", detail))

    def figures(self) -> dict[str, Any]:
        by = {o: sum(c.outcome == o for c in self.cases) for o in ("answered", "crashed")}
        per_channel = {
            ch: sum(c.channel == ch for c in self.cases)
            for ch in dict.fromkeys(c.channel for c in self.cases)
        }
        return {
            "tried": len(self.cases),
            "answered": by["answered"],
            "crashed": by["crashed"],
            "lost": self.lost,
            "acknowledged_checked": self.acknowledged,
            "per_channel": per_channel,
            "crashes": [
                f"{c.channel}: {c.name}: {c.detail}" for c in self.cases if c.outcome != "answered"
            ],
            **self.notes,
        }


# -- the service under attack --------------------------------------------------------------------
class Rig:
    """``vfm serve`` in a subprocess with a store that outlives kills, and the field side."""

    def __init__(self, folder: Path, data: Path, frame: pd.DataFrame) -> None:
        self.folder = folder
        self.frame = frame
        self.config = folder / "vfm.toml"
        self.config.write_text(f"""
[model]
name = "mm"
method = "ol"
history = "{data}"
history_until = "{SPLIT}"
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[http]
port = 0
token = "{TOKEN}"
[store]
path = "{folder / "store.sqlite"}"
synchronous = "normal"
checkpoint_every = 5
[inputs]
new_wells_burst = 50
new_wells_per_s = 5
""")
        self.log = folder / "serve.log"
        self.proc: ServeProcess | None = None
        self.bus: ZenohBus | None = None
        self.client: FieldClient | None = None
        self.http: httpx.Client | None = None
        sent = frame[frame["well"] == SENTINEL]
        self.sentinel_row = sent[["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]].iloc[0]
        self.sentinel_q = float(sent["q_total"].median())
        self.clock = frame["time"].max().to_pydatetime() + timedelta(days=30)
        self.tally = Tally()

    # life cycle
    def start(self) -> None:
        self.proc = ServeProcess(self.config, self.log).start(timeout=300)
        self.bus = ZenohBus.connect([self.proc.zenoh], block_wait_before_close_ms=600_000)
        self.client = FieldClient(self.bus, "vfm", match_timeout=20.0, track_latency=True)
        self.http = httpx.Client(base_url=self.proc.http_url, timeout=60)
        self.client.wait_for_service(SENTINEL)

    def close_link(self) -> None:
        for closer in (
            self.client.close if self.client else None,
            self.bus.close if self.bus else None,
            self.http.close if self.http else None,
        ):
            if closer is not None:
                try:
                    closer()
                except Exception:  # noqa: BLE001 - the peer is gone after a kill
                    pass
        self.client = self.bus = self.http = None

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.kill9()
        self.close_link()

    def stop(self) -> int | None:
        self.close_link()
        return self.proc.stop() if self.proc is not None else None

    # helpers
    def tick(self, minutes: float = 1.0) -> datetime:
        self.clock += timedelta(minutes=minutes)
        return self.clock

    def health(self) -> dict[str, Any]:
        assert self.http is not None
        return self.http.get("/health").json()

    def sentinel(self) -> bool:
        """A good sample of the sentinel well; True once its prediction came back."""
        assert self.client is not None
        t = self.tick()
        self.client.send_sample(SENTINEL, sample_of(t, self.sentinel_row))
        try:
            self.client.wait_for_prediction(SENTINEL, t, timeout=30.0)
            return True
        except TimeoutError:
            return False

    def put(self, key: str, payload: bytes | str) -> str | None:
        """Publish raw; None, or why the Zenoh library itself refused to send it."""
        assert self.bus is not None
        try:
            self.bus.put(key, payload)
            return None
        except (zenoh.ZError, ValueError) as exc:
            return str(exc)

    def log_text(self) -> str:
        return self.log.read_text(encoding="utf-8", errors="replace")


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    folder = tmp_path_factory.mktemp("adversarial")
    frame = validate_frame(
        simulate_field(wells=3, years=1, seed=3, hidden=["erosion:rate=0.3"]).observations
    ).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    r = Rig(folder, data, frame)
    r.start()
    try:
        yield r
    finally:
        r.stop()
        figures = r.tally.figures()
        print("\nadversarial suite:", json.dumps(figures, indent=1))
        target = os.environ.get("VFM_ADVERSARIAL_REPORT")
        if target:
            Path(target).write_text(json.dumps(figures, indent=1), encoding="utf-8")


# -- Zenoh ---------------------------------------------------------------------------------------
def _sample(t: Any, **changes: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "time": t.isoformat() if isinstance(t, datetime) else t,
        "choke": 0.4,
        "p_up": 120.0,
        "p_down": 30.0,
        "t_up": 60.0,
        "eta_gas": 0.1,
        "eta_oil": 0.6,
    }
    data.update(changes)
    return data


def _enc(payload: Any) -> bytes | str:
    return payload if isinstance(payload, bytes | str) else json.dumps(payload)


def _zenoh_case(
    rig: Rig, name: str, key: str, payload: Any, expect: str, *, accepted_kind: str = "sensors"
) -> None:
    """Send one message, then a sentinel; classify by what the counters say."""
    before = rig.health()
    refused = rig.put(key, _enc(payload() if callable(payload) else payload))
    if refused is not None:  # the Zenoh library would not send it: the service never saw it
        rig.tally.notes.setdefault("not deliverable (refused by the Zenoh client)", []).append(name)
        return
    answered = rig.sentinel()
    after = rig.health()
    rejected = {
        k: after["rejected"].get(k, 0) - before["rejected"].get(k, 0) for k in after["rejected"]
    }
    rejected = {k: v for k, v in rejected.items() if v}
    accepted = after["accepted"].get(accepted_kind, 0) - before["accepted"].get(accepted_kind, 0)
    if accepted_kind == "sensors":
        accepted -= 1  # the sentinel
    internal = after["events"].get("internal errors", 0) - before["events"].get(
        "internal errors", 0
    )
    if expect == "accepted":
        ok = answered and not rejected and accepted >= 1 and internal == 0
    else:
        ok = answered and rejected == {expect: 1} and internal == 0
    rig.tally.add(
        name,
        "zenoh",
        ok,
        "" if ok else f"expected {expect}; rejected {rejected}, accepted {accepted}",
    )


def test_zenoh_corpus(rig: Rig) -> None:
    s = f"vfm/{SENTINEL}/sensors"
    m = f"vfm/{SENTINEL}/measurements/mpfm"
    q = rig.sentinel_q
    now = datetime.now(UTC)
    cases: list[tuple[str, str, Any, str]] = []
    # times
    for text in (
        "9999-12-31T23:59:59-14:00",
        "0001-01-01T00:00:00+14:00",
        "1000-01-01T00:00:00Z",
        "1677-09-21T00:12:43Z",
        "2262-04-12T00:00:00Z",
        "2500-06-01T00:00:00Z",
    ):
        cases.append((f"sample time {text}", s, _sample(text), "time out of range"))
        cases.append((f"mpfm time {text}", m, {"time": text, "q_total": q}, "time out of range"))
    cases += [
        ("sample before 1970", s, _sample("1969-07-20T20:17:00Z"), "time out of range"),
        (
            "mpfm before 1970",
            m,
            {"time": "1901-01-01T00:00:00Z", "q_total": q},
            "time out of range",
        ),
        ("sample 23 h ahead", s, _sample(now + timedelta(hours=23)), "time in the future"),
        (
            "mpfm 3 days ahead",
            m,
            {"time": (now + timedelta(days=3)).isoformat(), "q_total": q},
            "time in the future",
        ),
        ("time as a huge number", s, _sample(1e30), "wrong type"),
        ("time null", s, _sample(None), "wrong type"),
        ("time offset +25:00", s, _sample("2017-03-01T00:00:00+25:00"), "wrong type"),
        ("time month 13", s, _sample("2017-13-01T00:00:00Z"), "wrong type"),
        ("time year +275760", s, _sample("+275760-09-13T00:00:00Z"), "wrong type"),
    ]
    # payloads
    cases += [
        ("JSON nested 50,000 deep", s, b"[" * 50_000, "too deeply nested"),
        ("JSON nested 100,000 deep", s, b"[" * 100_000, "payload too large"),
        (
            "JSON object nested 40 deep",
            s,
            json.dumps({**_sample(rig.tick()), "x": json.loads("[" * 40 + "]" * 40)}),
            "too deeply nested",
        ),
        ("20 MB payload", s, b'{"time": "' + b"x" * 20_000_000 + b'"}', "payload too large"),
        (
            "70 kB payload",
            m,
            json.dumps({"time": rig.tick().isoformat(), "q_total": q, "pad": "y" * 70_000}),
            "payload too large",
        ),
        ("empty payload", s, b"", "malformed JSON"),
        ("binary garbage", s, bytes(range(256)), "malformed JSON"),
        (
            "UTF-16 JSON (Python reads it)",
            s,
            lambda: json.dumps(_sample(rig.tick())).encode("utf-16"),
            "accepted",
        ),
        ("JSON string", s, b'"hello"', "not a JSON object"),
        ("JSON array", m, b"[1, 2, 3]", "not a JSON object"),
        ("NaN pressure", s, json.dumps(_sample(rig.tick(), p_up=float("nan"))), "not finite"),
        (
            "Infinity temperature",
            s,
            json.dumps(_sample(rig.tick(), t_up=float("inf"))),
            "not finite",
        ),
        (
            "400-digit integer pressure",
            s,
            json.dumps(_sample(rig.tick(), p_up=10**400)),
            "not finite",
        ),
        (
            "400-digit integer rate",
            m,
            json.dumps({"time": rig.tick().isoformat(), "q_total": 10**400}),
            "not finite",
        ),
        (
            "5000-digit integer",
            s,
            b'{"time": "2017-01-01T00:00:00Z", "p_up": ' + b"9" * 5000 + b"}",
            "malformed JSON",
        ),
        ("bool choke", s, _sample(rig.tick(), choke=True), "wrong type"),
        ("string pressure", s, _sample(rig.tick(), p_up="120"), "wrong type"),
        ("object pressure", s, _sample(rig.tick(), p_up={"v": 1}), "wrong type"),
        ("missing field", s, {"time": rig.tick().isoformat(), "choke": 0.4}, "missing field"),
        ("zero pressure", s, _sample(rig.tick(), p_down=0.0), "negative or zero pressure"),
        # an input outside its physical span: taken, an out_of_range fault (stood in for)
        (  # (a taken sample gets its time when sent: after the refused ones built above)
            "negative pressure",
            s,
            lambda: json.dumps(_sample(rig.tick(), p_down=-1.0)),
            "accepted",
        ),
        ("p_down above p_up", s, _sample(rig.tick(), p_down=500.0), "p_down >= p_up"),
        ("choke 7", s, lambda: json.dumps(_sample(rig.tick(), choke=7)), "accepted"),
        (
            "fractions above 1",
            s,
            _sample(rig.tick(), eta_gas=0.7, eta_oil=0.7),
            "fractions sum above 1",
        ),
        (
            "temperature -300 degC",
            s,
            lambda: json.dumps(_sample(rig.tick(), t_up=-300.0)),
            "accepted",
        ),
        (
            "3,000 extra fields",
            s,
            lambda: json.dumps({**_sample(rig.tick()), **{f"x{i}": i for i in range(3000)}}),
            "accepted",
        ),
    ]
    # rates (the sentinel's median is q)
    cases += [
        ("rate 1e300", m, {"time": rig.tick().isoformat(), "q_total": 1e300}, "implausible rate"),
        (
            "rate above the cap",
            m,
            {"time": rig.tick().isoformat(), "q_total": 2e7},
            "implausible rate",
        ),
        ("rate negative", m, {"time": rig.tick().isoformat(), "q_total": -1.0}, "negative rate"),
    ]
    # keys and well ids
    forged = "W9\nERROR vfm.service: forged line"
    cases += [
        (
            "well id with a forged log line",
            f"vfm/{forged}/sensors",
            _sample(rig.tick()),
            "unparseable key",
        ),
        ("well id with NUL", "vfm/W\x009/sensors", _sample(rig.tick()), "unparseable key"),
        ("well id with a tab", "vfm/W\t9/sensors", _sample(rig.tick()), "unparseable key"),
        (
            "well id with an escape sequence",
            "vfm/W\x1b[31m9/sensors",
            _sample(rig.tick()),
            "unparseable key",
        ),
        (
            "well id with a right-to-left override",
            "vfm/W\u202e9/sensors",
            _sample(rig.tick()),
            "unparseable key",
        ),
        ("well id ..", "vfm/../sensors", _sample(rig.tick()), "unparseable key"),
        ("well id .", "vfm/./sensors", _sample(rig.tick()), "unparseable key"),
        ("well id of 10 kB", f"vfm/{'W' * 10_000}/sensors", _sample(rig.tick()), "unparseable key"),
        (
            "well id of 129 characters",
            f"vfm/{'W' * 129}/sensors",
            _sample(rig.tick()),
            "unparseable key",
        ),
        ("well id with a leading space", "vfm/ W9/sensors", _sample(rig.tick()), "unparseable key"),
        (
            "unknown source",
            f"vfm/{SENTINEL}/measurements/guess",
            {"time": rig.tick().isoformat(), "q_total": q},
            "unknown source",
        ),
        ("key too deep", f"vfm/{SENTINEL}/sensors/x/y", _sample(rig.tick()), "unparseable key"),
        ("key too short", "vfm/W02", _sample(rig.tick()), "unparseable key"),
        ("well id in Greek (valid)", "vfm/Πηγάδι-1/sensors", _sample(rig.tick()), "accepted"),
    ]
    for name, key, payload, expect in cases:
        _zenoh_case(rig, name, key, payload, expect)
    # stateful cases on the sentinel: order, duplicates, plausible rates against its median
    t = rig.tick()
    rig.put(s, json.dumps(_sample(t)))
    _zenoh_case(rig, "the same sample again", s, _sample(t), "duplicate")
    _zenoh_case(rig, "an older sample", s, _sample(t - timedelta(hours=1)), "time going backwards")
    for name, rate, expect in (
        ("rate 30 times the median", 30 * q, "implausible rate"),
        ("rate zero (a stuck meter)", 0.0, "implausible rate"),
        ("rate a 30th of the median", q / 30, "implausible rate"),
        ("rate at the median", q, "accepted"),
    ):
        t = rig.tick()
        _zenoh_case(
            rig,
            name,
            m,
            {"time": t.isoformat(), "q_total": rate},
            expect,
            accepted_kind="measurements",
        )
    _zenoh_case(
        rig, "the same measurement again", m, {"time": t.isoformat(), "q_total": q}, "duplicate"
    )
    # the well's own refusals are counted under it, for its alarm on the workbench
    own = rig.http.get(f"/wells/{SENTINEL}").json()["rejected"]
    assert own.get("implausible rate", 0) >= 3 and own.get("duplicate", 0) >= 2, own
    _zenoh_case(
        rig,
        "a measurement with no sample near it",
        m,
        {"time": (t - timedelta(days=20)).isoformat(), "q_total": q},
        "no sensor sample within tolerance",
    )
    # a sample from the future holds back the well's samples only within inputs.max_future_s
    wall = datetime.now(UTC).replace(microsecond=0)
    _zenoh_case(
        rig,
        "new well, sample 23 h ahead",
        "vfm/FUT/sensors",
        _sample(wall + timedelta(hours=23)),
        "time in the future",
    )
    _zenoh_case(rig, "then a real-time sample", "vfm/FUT/sensors", _sample(wall), "accepted")
    _zenoh_case(
        rig,
        "then one 4 min ahead (clock skew)",
        "vfm/FUT/sensors",
        _sample(wall + timedelta(minutes=4)),
        "accepted",
    )
    _zenoh_case(
        rig,
        "then a real-time one (held back)",
        "vfm/FUT/sensors",
        _sample(wall + timedelta(seconds=1)),
        "time going backwards",
    )
    # sensor blocks (many samples in one message): bad rows refused alone, bad blocks whole
    b = "vfm/BLK/sensors"

    def block(n: int = 3, **rows: Any) -> dict[str, Any]:
        times = [rig.tick().isoformat() for _ in range(n)]
        data: dict[str, Any] = {"time": times}
        for name, value in _sample(times[0]).items():
            if name != "time":
                data[name] = [value] * n
        for name, column in rows.items():
            data[name] = column
        return data

    _zenoh_case(rig, "a block of three samples", b, block, "accepted")
    _zenoh_case(
        rig,
        "a block with one row p_down >= p_up",
        b,
        lambda: block(p_down=[30.0, 130.0, 30.0]),
        "p_down >= p_up",
    )
    _zenoh_case(
        rig,
        "a block with a nested array in a row",
        b,
        lambda: block(choke=[[0.4], 0.4, 0.4]),
        "wrong type",
    )
    _zenoh_case(
        rig,
        "a block with a 400-digit time",
        b,
        lambda: {**block(), "time": [10**400, rig.tick().isoformat(), rig.tick().isoformat()]},
        "not finite",
    )
    _zenoh_case(
        rig,
        "a block with a row out of order",
        b,
        lambda: (lambda d: {**d, "time": [d["time"][1], d["time"][0], d["time"][2]]})(block()),
        "time going backwards",
    )
    _zenoh_case(
        rig,
        "a block with arrays of two lengths",
        b,
        lambda: block(p_up=[120.0, 120.0]),
        "malformed block",
    )
    _zenoh_case(
        rig, "a block with one field a number", b, lambda: block(p_up=120.0), "malformed block"
    )
    _zenoh_case(
        rig,
        "an empty block",
        b,
        {
            "time": [],
            "choke": [],
            "p_up": [],
            "p_down": [],
            "t_up": [],
            "eta_gas": [],
            "eta_oil": [],
        },
        "malformed block",
    )
    _zenoh_case(
        rig,
        "a block of 1,001 rows",
        b,
        lambda: {
            "time": ["2020"] * 1001,
            **{k: [1] * 1001 for k in ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")},
        },
        "block too large",
    )
    # nothing forged reached the log; the escaped id is there
    log = rig.log_text()
    assert not re.search(r"^ERROR vfm\.service: forged", log, re.M), "a forged log line"
    assert "\\nERROR vfm.service: forged" in log
    assert "\x00" not in log and "\x1b" not in log
    assert rig.health()["events"].get("internal errors", 0) == 0


# -- HTTP ----------------------------------------------------------------------------------------
def _http_case(
    rig: Rig,
    name: str,
    method: str,
    path: str,
    status: int,
    reason: str | None = "any",
    **kwargs: Any,
) -> httpx.Response | None:
    assert rig.http is not None
    try:
        r = rig.http.request(method, path, **kwargs)
    except httpx.HTTPError as exc:
        rig.tally.add(name, "http", False, f"no answer: {exc}")
        return None
    ok = r.status_code == status and r.status_code in DOCUMENTED
    detail = ""
    if r.status_code >= 400:
        try:
            body = r.json()
            ok = ok and isinstance(body.get("detail"), str) and body["detail"].endswith(".")
            ok = ok and (reason == "any" or body.get("reason") == reason)
            detail = f"{r.status_code} {body}"
        except ValueError:
            ok, detail = False, f"{r.status_code} not JSON: {r.text[:80]}"
    rig.tally.add(
        name, "http", ok, "" if ok else f"expected {status} {reason}; got {detail or r.status_code}"
    )
    return r


def test_http_corpus(rig: Rig) -> None:
    post = f"/wells/{SENTINEL}/well-tests"
    q = rig.sentinel_q
    t = rig.tick()
    assert rig.sentinel()
    good_time = rig.clock.isoformat()
    for text in (
        "9999-12-31T23:59:59-14:00",
        "0001-01-01T00:00:00+14:00",
        "1000-01-01T00:00:00Z",
        "2300-01-01T00:00:00Z",
        "1950-01-01T00:00:00Z",
    ):
        _http_case(
            rig,
            f"well test at {text}",
            "POST",
            post,
            422,
            "time out of range",
            json={"time": text, "q_total": q},
            headers=AUTH,
        )
        for bound in ("start", "end"):
            _http_case(
                rig,
                f"history {bound}={text}",
                "GET",
                f"/wells/{SENTINEL}/history",
                422 if not text.startswith("1950") else 200,
                "any",
                params={bound: text},
            )
            _http_case(
                rig,
                f"history.csv {bound}={text}",
                "GET",
                f"/wells/{SENTINEL}/history.csv",
                422 if not text.startswith("1950") else 200,
                "any",
                params={bound: text},
            )
    deep = b"[" * 50_000 + b"]" * 50_000
    cases: list[tuple[str, str, str, int, str | None, dict[str, Any]]] = [
        (
            "well test 20 MB body",
            "POST",
            post,
            413,
            "payload too large",
            {"content": b"x" * 20_000_000, "headers": AUTH},
        ),
        (
            "well test nested 50,000 deep",
            "POST",
            post,
            413,
            "payload too large",
            {"content": deep, "headers": AUTH},
        ),
        (
            "well test nested 20,000 deep",
            "POST",
            post,
            422,
            "too deeply nested",
            {"content": b"[" * 20_000, "headers": AUTH},
        ),
        (
            "model change nested 20,000 deep",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            "too deeply nested",
            {"content": b"[" * 20_000, "headers": {**AUTH, "content-type": "application/json"}},
        ),
        (
            "well test chunked 100 kB",
            "POST",
            post,
            413,
            "payload too large",
            {"content": iter([b"{" + b" " * 50_000, b" " * 50_000 + b"}"]), "headers": AUTH},
        ),
        (
            "well test malformed",
            "POST",
            post,
            422,
            "malformed JSON",
            {"content": b"{oops", "headers": AUTH},
        ),
        (
            "well test rate 1e300",
            "POST",
            post,
            422,
            "implausible rate",
            {"json": {"time": good_time, "q_total": 1e300}, "headers": AUTH},
        ),
        (
            "well test rate 30x",
            "POST",
            post,
            422,
            "implausible rate",
            {"json": {"time": good_time, "q_total": 30 * q}, "headers": AUTH},
        ),
        (
            "well test rate zero",
            "POST",
            post,
            422,
            "implausible rate",
            {"json": {"time": good_time, "q_total": 0.0}, "headers": AUTH},
        ),
        (
            "well test 400-digit rate",
            "POST",
            post,
            422,
            "not finite",
            {
                "content": b'{"time": "2017-01-01T00:00:00Z", "q_total": 1' + b"0" * 400 + b"}",
                "headers": AUTH,
            },
        ),
        (
            "well test 23 h ahead",
            "POST",
            post,
            422,
            "time in the future",
            {
                "json": {
                    "time": (datetime.now(UTC) + timedelta(hours=23)).isoformat(),
                    "q_total": q,
                },
                "headers": AUTH,
            },
        ),
        (
            "well test to a typo",
            "POST",
            "/wells/W2/well-tests",
            404,
            "unknown well",
            {"json": {"time": good_time, "q_total": q}, "headers": AUTH},
        ),
        (
            "well test without a token",
            "POST",
            post,
            401,
            None,
            {"json": {"time": good_time, "q_total": q}},
        ),
        (
            "well test with a wrong token",
            "POST",
            post,
            401,
            None,
            {
                "json": {"time": good_time, "q_total": q},
                "headers": {"Authorization": "Bearer x" * 3},
            },
        ),
        ("well id with a newline", "GET", "/wells/W%0AERROR", 422, "unparseable key", {}),
        ("well id with NUL", "GET", "/wells/W%009", 422, "unparseable key", {}),
        ("well id of 10 kB", "GET", "/wells/" + "W" * 10_000, 422, "unparseable key", {}),
        ("well id ..", "GET", "/wells/%2E%2E", 422, "unparseable key", {}),
        (
            "well test to a 10 kB id",
            "POST",
            "/wells/" + "W" * 10_000 + "/well-tests",
            422,
            "unparseable key",
            {"json": {"time": good_time, "q_total": q}, "headers": AUTH},
        ),
        ("unknown well", "GET", "/wells/NOPE", 404, None, {}),
        ("unknown path", "GET", "/nothing/here", 404, None, {}),
        ("wrong method", "PATCH", "/wells", 405, None, {}),
        (
            "history end before start",
            "GET",
            f"/wells/{SENTINEL}/history",
            422,
            "wrong type",
            {"params": {"start": "2017-02-01", "end": "2017-01-01"}},
        ),
        (
            "history limit 0",
            "GET",
            f"/wells/{SENTINEL}/history",
            422,
            "any",
            {"params": {"limit": 0}},
        ),
        (
            "history limit 10**30",
            "GET",
            f"/wells/{SENTINEL}/history",
            422,
            "any",
            {"params": {"limit": 10**30}},
        ),
        (
            "history start garbage",
            "GET",
            f"/wells/{SENTINEL}/history",
            422,
            "wrong type",
            {"params": {"start": "yesterday"}},
        ),
        (
            "model pbl:1ns",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            None,
            {"json": {"method": "pbl:1ns"}, "headers": AUTH},
        ),
        (
            "model pbl:30min",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            None,
            {"json": {"method": "pbl:30min"}, "headers": AUTH},
        ),
        (
            "model pbl:auto",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            None,
            {"json": {"method": "pbl:auto"}, "headers": AUTH},
        ),
        (
            "model unknown method",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            None,
            {"json": {"method": "magic"}, "headers": AUTH},
        ),
        (
            "model mtl",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            None,
            {"json": {"model": "mtl"}, "headers": AUTH},
        ),
        (
            "model effect from a module",
            "PUT",
            f"/wells/{SENTINEL}/model",
            403,
            None,
            {"json": {"effects": ["os:system"]}, "headers": AUTH},
        ),
        (
            "model extra field",
            "PUT",
            f"/wells/{SENTINEL}/model",
            422,
            "any",
            {"json": {"method": "ol", "shell": "rm"}, "headers": AUTH},
        ),
        ("retire without a token", "DELETE", f"/wells/{SENTINEL}", 401, None, {}),
        ("retire an unknown well", "DELETE", "/wells/NOPE", 404, None, {"headers": AUTH}),
    ]
    for name, method, path, status, reason, kwargs in cases:
        _http_case(rig, name, method, path, status, reason, **kwargs)
    # the worker still answers after all of that
    rig.tally.add("worker answers after the HTTP corpus", "http", rig.sentinel())
    # a good well test, then the same again
    t = rig.tick()
    assert rig.client is not None
    rig.client.send_sample(SENTINEL, sample_of(t, rig.sentinel_row))
    rig.client.wait_for_prediction(SENTINEL, t, 30)
    ok = _http_case(
        rig,
        "a good well test",
        "POST",
        post,
        200,
        json={"time": t.isoformat(), "q_total": q * 1.02},
        headers=AUTH,
    )
    assert ok is not None and ok.status_code == 200
    _http_case(
        rig,
        "the same well test again",
        "POST",
        post,
        409,
        "duplicate",
        json={"time": t.isoformat(), "q_total": q * 1.02},
        headers=AUTH,
    )
    # retire a new well: then its messages are refused; purge frees the id
    rig.put("vfm/RET/sensors", json.dumps(_sample(rig.tick())))
    wait_until(
        lambda: rig.http is not None and rig.http.get("/wells/RET").status_code == 200, 20, "RET"
    )
    _http_case(rig, "retire a well", "DELETE", "/wells/RET", 200, headers=AUTH)
    _zenoh_case(
        rig, "a sample of the retired well", "vfm/RET/sensors", _sample(rig.tick()), "retired well"
    )
    _http_case(
        rig,
        "a well test of the retired well",
        "POST",
        "/wells/RET/well-tests",
        422,
        "retired well",
        json={"time": rig.clock.isoformat(), "q_total": q},
        headers=AUTH,
    )
    _http_case(rig, "retire it again", "DELETE", "/wells/RET", 404, None, headers=AUTH)
    assert rig.health()["events"].get("internal errors", 0) == 0


# -- floods --------------------------------------------------------------------------------------
def test_floods_are_bounded_and_every_message_is_answered(rig: Rig) -> None:
    assert rig.proc is not None and rig.client is not None
    # 1. one well as fast as Zenoh takes it, for 3 s, while the sentinel sends every 50 ms
    before = rig.health()
    flood_sent = 0
    stop = threading.Event()

    def flood() -> None:
        nonlocal flood_sent
        with ZenohBus.connect([rig.proc.zenoh]) as bus:  # type: ignore[union-attr]
            base = rig.clock + timedelta(days=1)
            i = 0
            while not stop.is_set():
                bus.put("vfm/FLOOD/sensors", json.dumps(_sample(base + timedelta(microseconds=i))))
                i += 1
                flood_sent = i
            # a last sample of the sentinel on the same link: once it is answered, every
            # flood message before it reached the service (a session closed with messages
            # still queued drops them on the sender's side)
            marker = rig.tick()
            bus.put(
                f"vfm/{SENTINEL}/sensors", sample_of(marker, rig.sentinel_row).model_dump_json()
            )
            rig.client.wait_for_prediction(SENTINEL, marker, timeout=300)  # type: ignore[union-attr]

    thread = threading.Thread(target=flood)
    thread.start()
    latency: list[float] = []
    answered = True
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        t0 = time.perf_counter()
        answered &= rig.sentinel()
        latency.append(time.perf_counter() - t0)
        time.sleep(0.05)
    stop.set()
    thread.join(30)

    def counts() -> tuple[int, int]:
        """Messages received since ``before``, and those answered (accepted or counted)."""
        h = rig.health()
        received = h["received"] - before["received"]
        answered = (
            sum(h["accepted"].values())
            - sum(before["accepted"].values())
            + h["rejected_total"]
            - before["rejected_total"]
        )
        return received, answered

    wait_until(lambda: counts()[0] == counts()[1], 120, "every flood message answered")
    received, answered_n = counts()
    rig.tally.add(
        "one well floods over Zenoh",
        "flood",
        answered and received == answered_n and received == flood_sent + len(latency) + 1,
        f"sent {flood_sent}, received {received}, answered {answered_n}",
    )
    rig.tally.notes["flood: messages sent, received"] = [flood_sent, received]
    rig.tally.notes["flood: good well round trip during it, ms (p50, max)"] = [
        round(float(np.percentile(latency, 50)) * 1000, 1),
        round(max(latency) * 1000, 1),
    ]
    # 2. thousands of new well names: a few are created (the burst and the rate), the rest
    # refused and counted; the cap of wells holds
    before = rig.health()
    n_names = 3000
    with ZenohBus.connect([rig.proc.zenoh]) as bus:
        bus.matching(f"vfm/{SENTINEL}/sensors", 20.0)
        for i in range(n_names):
            bus.session.put(
                f"vfm/NAME{i:05d}/sensors",
                json.dumps(_sample(rig.clock)),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
    wait_until(
        lambda: (
            (rig.health()["rejected_total"] - before["rejected_total"])
            + (rig.health()["accepted"].get("sensors", 0) - before["accepted"].get("sensors", 0))
            >= n_names
        ),
        60,
        "every name accounted for",
    )
    after = rig.health()
    created = after["wells"] - before["wells"]
    refused = after["rejected"].get("too many new wells", 0) - before["rejected"].get(
        "too many new wells", 0
    )
    rig.tally.add(
        "3,000 new well names",
        "flood",
        created + refused == n_names and created <= 50 + 5 * 60,
        f"{created} created, {refused} refused",
    )
    rig.tally.notes["names flood: created, refused"] = [created, refused]
    rig.tally.add("worker answers after the floods", "flood", rig.sentinel())
    # 3. concurrent HTTP posts: every one answered with a documented status
    statuses: list[int] = []
    lock = threading.Lock()
    base = rig.tick()
    assert rig.proc is not None

    def poster(k: int) -> None:
        with httpx.Client(base_url=rig.proc.http_url, timeout=60) as http:  # type: ignore[union-attr]
            for j in range(25):
                t = base + timedelta(seconds=k * 100 + j % 20)  # some repeat: duplicates
                try:
                    r = http.post(
                        f"/wells/{SENTINEL}/well-tests",
                        json={"time": t.isoformat(), "q_total": rig.sentinel_q},
                        headers=AUTH,
                    )
                    code = r.status_code
                except httpx.HTTPError:
                    code = -1
                with lock:
                    statuses.append(code)

    posters = [threading.Thread(target=poster, args=(k,)) for k in range(12)]
    for p in posters:
        p.start()
    for p in posters:
        p.join(120)
    bad = [c for c in statuses if c not in DOCUMENTED]
    rig.tally.add(
        "300 concurrent HTTP well tests",
        "flood",
        not bad and len(statuses) == 300,
        f"undocumented: {bad[:5]}",
    )
    rig.tally.notes["http flood statuses"] = {
        str(c): statuses.count(c) for c in sorted(set(statuses))
    }
    assert rig.health()["events"].get("internal errors", 0) == 0


# -- kill -9 at several moments --------------------------------------------------------------------
@dataclass
class Acks:
    """What the service acknowledged: (well, source, time ns) of measurements and well tests,
    and those found missing after a restart."""

    keys: set[tuple[str, str, int]] = field(default_factory=set)
    missing: set[tuple[str, str, int]] = field(default_factory=set)


def _stream(
    rig: Rig, rows: pd.DataFrame, acks: Acks, stop: threading.Event, settle: bool = False
) -> None:
    """Stream rows; a measurement counts as acknowledged once a prediction of a later
    sample of its well came back (predictions are published only after the commit)."""
    client = rig.client
    assert client is not None
    sent: dict[str, list[tuple[int, tuple[str, str, int]]]] = {}
    last_sample: dict[str, int] = {}
    try:
        for row in rows.itertuples(index=False):
            if stop.is_set():
                break
            t_ns = to_ns(row.time.to_pydatetime())
            well = str(row.well)
            if last_sample.get(well) != t_ns:
                client.send_sample(
                    well,
                    sample_of(
                        row.time.to_pydatetime(),
                        [row.choke, row.p_up, row.p_down, row.t_up, row.eta_gas, row.eta_oil],
                    ),
                )
                last_sample[well] = t_ns
            if (
                isinstance(row.source, str)
                and row.source in ("mpfm", "well_test")
                and np.isfinite(row.q_total)
            ):
                client.send_measurement(
                    well,
                    row.source,
                    Measurement(time=row.time.to_pydatetime(), q_total=float(row.q_total)),
                )
                sent.setdefault(well, []).append((t_ns, (well, row.source, t_ns)))
    except Exception:  # noqa: BLE001 - the service was killed under us
        pass
    if settle:  # wait for the predictions of the last samples
        expected = [(w, t) for w, t in last_sample.items()]
        client.wait_for_answers(expected, idle_timeout=5.0, final_timeout=120.0)
    for well, items in sent.items():
        latest = client.latest.get(well)
        if latest is None:
            continue
        # measurement at t was sent before the sample after t; a prediction at a later
        # sample than t means that sample, and so the measurement, was committed
        acks.keys.update(key for t, key in items if t < latest)


def _check_restart(rig: Rig, acks: Acks, name: str) -> None:
    rig.start()
    con = sqlite3.connect(f"{(rig.folder / 'store.sqlite').resolve().as_uri()}?mode=ro", uri=True)
    stored = set(con.execute("SELECT well, source, time_ns FROM measurements").fetchall())
    con.close()
    missing = acks.keys - stored
    acks.missing |= missing
    rig.tally.acknowledged = len(acks.keys)
    rig.tally.lost = len(acks.missing)
    healthy = rig.health()["status"] == "ok" and rig.sentinel()
    rig.tally.add(
        f"restart after kill -9 {name}", "kill", healthy and not missing, f"{len(missing)} lost"
    )


def test_kill9_at_several_moments(rig: Rig) -> None:
    rows = rig.frame[
        (rig.frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")) & rig.frame["well"].isin(STREAMED)
    ]
    rows = rows.sort_values("time", kind="stable").reset_index(drop=True)
    parts = np.array_split(np.arange(len(rows)), 5)
    # 1. while a field streams
    acks = Acks()
    stop = threading.Event()
    streamer = threading.Thread(target=_stream, args=(rig, rows.iloc[parts[0]], acks, stop))
    streamer.start()
    assert rig.client is not None
    wait_until(
        lambda: rig.client is not None and rig.client.count > 150, 60, "a part of the stream"
    )
    rig.kill9()
    stop.set()
    streamer.join(30)
    _check_restart(rig, acks, "while a field streams")
    # 2. during a model change (the fit of mm+erosion on W01's history)
    _stream(rig, rows.iloc[parts[1]], acks, threading.Event(), settle=True)
    answers: list[int] = []

    def change() -> None:
        try:
            assert rig.proc is not None
            r = httpx.put(
                f"{rig.proc.http_url}/wells/W01/model",
                json={"model": "ham", "effects": ["erosion"]},
                headers=AUTH,
                timeout=120,
            )
            answers.append(r.status_code)
            if r.status_code == 200:
                rig.tally.notes.setdefault("model change fit_s", []).append(
                    r.json()["holdout"].get("fit_s")
                )
        except httpx.HTTPError:
            answers.append(-1)

    changer = threading.Thread(target=change)
    fitting = rig.log_text().count("Model change of W01: fitting")
    changer.start()
    wait_until(
        lambda: rig.log_text().count("Model change of W01: fitting") > fitting, 60, "the fit"
    )
    rig.kill9()  # the fit (of a network: seconds) runs now
    changer.join(30)
    _check_restart(rig, acks, "during a model change")
    rig.tally.notes["model change killed in its fit: its caller got"] = list(answers)
    # 3. during a flood (samples and measurements of both wells, and HTTP well tests)
    stop = threading.Event()
    streamer = threading.Thread(target=_stream, args=(rig, rows.iloc[parts[2]], acks, stop))
    acked_http: list[tuple[str, str, int]] = []

    def post_tests() -> None:
        assert rig.proc is not None
        with httpx.Client(base_url=rig.proc.http_url, timeout=30) as http:
            for j in range(200):
                t = rig.clock + timedelta(hours=1 + j)
                try:
                    rig.client.send_sample(SENTINEL, sample_of(t, rig.sentinel_row))  # type: ignore[union-attr]
                    r = http.post(
                        f"/wells/{SENTINEL}/well-tests",
                        json={"time": t.isoformat(), "q_total": rig.sentinel_q},
                        headers=AUTH,
                    )
                except Exception:  # noqa: BLE001 - killed
                    return
                if r.status_code in (200, 202):
                    acked_http.append((SENTINEL, "well_test", to_ns(t)))

    poster = threading.Thread(target=post_tests)
    streamer.start()
    poster.start()
    time.sleep(1.5)
    rig.kill9()
    stop.set()
    streamer.join(30)
    poster.join(30)
    rig.clock += timedelta(hours=300)
    acks.keys.update(acked_http)
    _check_restart(rig, acks, "during a flood")
    rig.tally.notes["well tests acknowledged in the flood before the kill"] = len(acked_http)
    # 4. right after acknowledged well tests
    _stream(rig, rows.iloc[parts[3]], acks, threading.Event(), settle=True)
    assert rig.http is not None and rig.client is not None
    for _ in range(5):
        t = rig.tick(30)
        rig.client.send_sample(SENTINEL, sample_of(t, rig.sentinel_row))
        r = rig.http.post(
            f"/wells/{SENTINEL}/well-tests",
            json={"time": t.isoformat(), "q_total": rig.sentinel_q * 0.98},
            headers=AUTH,
        )
        if r.status_code in (200, 202):
            acks.keys.add((SENTINEL, "well_test", to_ns(t)))
    rig.kill9()
    _check_restart(rig, acks, "right after acknowledged well tests")
    # 5. a SIGTERM during a model change: a clean stop (exit 0, no abort), then a restart
    _stream(rig, rows.iloc[parts[4]], acks, threading.Event(), settle=True)
    changer = threading.Thread(target=change)
    answers.clear()
    fitting = rig.log_text().count("Model change of W01: fitting")
    changer.start()
    wait_until(
        lambda: rig.log_text().count("Model change of W01: fitting") > fitting, 60, "the fit"
    )
    assert rig.proc is not None and rig.proc.proc is not None
    rig.proc.proc.send_signal(signal.SIGTERM)
    try:
        code = rig.proc.proc.wait(60)
    except Exception:  # noqa: BLE001 - did not stop: a crash
        code = None
    changer.join(60)
    rig.close_link()
    rig.proc.stop()
    rig.tally.add("SIGTERM during a model change stops cleanly", "kill", code == 0, f"exit {code}")
    # in-flight requests get http.shutdown_grace_s: the change finishes (200) or is cut off
    rig.tally.notes["model change under SIGTERM: its caller got"] = list(answers)
    _check_restart(rig, acks, "after that SIGTERM")
    assert "terminate called" not in rig.log_text()


def test_figures(rig: Rig) -> None:
    figures = rig.tally.figures()
    print(
        "\nadversarial figures:",
        json.dumps(
            {
                k: figures[k]
                for k in ("tried", "answered", "crashed", "lost", "acknowledged_checked")
            }
        ),
    )
    assert figures["tried"] >= 150
    assert figures["crashed"] == 0, figures["crashes"]
    assert figures["lost"] == 0
    assert figures["acknowledged_checked"] > 100
