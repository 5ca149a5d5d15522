"""Benchmark: what a model change's trial decides on fields the tests do not use.

Prints one line per field and a summary; asserts nothing. For each simulated one-well field
(seeds and erosion rates that tests/test_service_trial.py does not use) a service runs the
well on ``mm`` with the method named, fitted on the history before ``SPLIT`` and replayed to
``MID``; then, through the HTTP API as an operator would:

1. ``PUT /wells/W01/model`` with ``mm+erosion`` (confirmed with ``confirm_worse`` when its
   held-out check says worse), 45 days replayed, the trial read from ``GET /wells/W01``;
2. the effect taken away again (the deliberately wrong change on an eroding field), 45 more
   days, that trial read.

On an eroding field the first change should be kept and the second rolled back; on a clean
field (``--clean``) neither should be rolled back (a false rollback happens at the rule's
alpha, 5 %, per trial at most).

With ``--wrong <method>`` (e.g. ``pbl:182d``), a second kind of field: two wells on ``mm``
with ``ol``, and at ``MID`` two changes at once over HTTP: W01 gets ``erosion`` (the right
change on an eroding field) and W02 is switched to ``<method>`` (a method that re-learns too
seldom for a wearing choke: the deliberately wrong change; since s54 its held-out check,
each method learning over the latest fifth, asks first and the change is confirmed), 45
days replayed, both trials read. Eroding
fields: ``--wrong-seeds``; clean ones, where the method change is harmless or nearly so:
``--wrong-clean``.

Usage::

    python benchmarks/bench_trials.py [--seeds 31,32,33,34] [--rate 0.3] [--methods ol,bayes]
                                      [--clean 41,42,43,44]
    python benchmarks/bench_trials.py --seeds '' --clean '' --wrong pbl:182d \
                                      [--wrong-seeds 51,52,53,54,55] [--wrong-clean 61,62,63,64]
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import pandas as pd

from replay.replayer import replay_frame
from service.app import running
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

TOKEN = "bench-trial-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SPLIT, MID = "2016-06-01", "2016-12-01"


def _ts(text: str | pd.Timestamp) -> pd.Timestamp:
    return pd.Timestamp(text, tz="UTC") if not isinstance(text, pd.Timestamp) else text


def run_case(seed: int, hidden: list[str], method: str, folder: Path) -> list[dict[str, Any]]:
    """The two changes on one field; each trial as GET /wells/W01 shows it at its end."""
    frame = validate_frame(
        simulate_field(wells=1, years=1.5, seed=seed, hidden=hidden).observations
    ).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": method, "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"checkpoint_every": 50},
    )
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    out = []
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        replay_frame(
            frame[frame.time < _ts(MID)], bus=bus, start=SPLIT, progress=False, idle_timeout=2.0
        )
        start = _ts(MID)
        for effects in (["erosion"], []):
            until = start + pd.Timedelta(days=45)
            body = {"effects": effects}
            r = http.put("/wells/W01/model", json=body, headers=AUTH)
            asked = r.status_code == 409
            if asked:  # the held-out check says worse: the operator confirms
                r = http.put("/wells/W01/model", json=body | {"confirm_worse": True}, headers=AUTH)
            r.raise_for_status()
            holdout = r.json()["holdout"]
            part = frame[(frame.time >= start) & (frame.time < until)]
            replay_frame(part, bus=bus, progress=False, idle_timeout=2.0)
            trial = http.get("/wells/W01").json()["trial"]
            out.append(
                {
                    "change": "+erosion" if effects else "-erosion",
                    "holdout": (holdout.get("before"), holdout.get("after")),
                    "confirmed": asked,
                    "n": trial["n"],
                    "mape": trial["mape"],
                    "shadow_mape": trial["shadow_mape"],
                    "p": trial.get("p_value"),
                    "outcome": trial["outcome"],
                }
            )
            start = until
    return out


def run_pair(seed: int, hidden: list[str], wrong: str, folder: Path) -> list[dict[str, Any]]:
    """The right and the wrong change at once on a two-well field (``--wrong``); each
    trial as GET /wells/{well} shows it 45 days of data later."""
    frame = validate_frame(
        simulate_field(wells=2, years=1.5, seed=seed, hidden=hidden).observations
    ).frame
    data = folder / "field.parquet"
    frame.to_parquet(data)
    settings = loopback_settings(
        folder,
        model={"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT},
        http={"token": TOKEN},
        store={"checkpoint_every": 50},
    )
    bus = MemoryTransport(settings.prefix, settings.queues.receive_capacity)
    changes = {"W01": ("+erosion", {"effects": ["erosion"]}), "W02": (wrong, {"method": wrong})}
    out = []
    with running(settings, bus) as svc, httpx.Client(base_url=svc.http_url, timeout=300) as http:
        replay_frame(
            frame[frame.time < _ts(MID)], bus=bus, start=SPLIT, progress=False, idle_timeout=2.0
        )
        asked, holdouts = {}, {}
        for well, (_, body) in changes.items():
            r = http.put(f"/wells/{well}/model", json=body, headers=AUTH)
            asked[well] = r.status_code == 409
            if asked[well]:  # the held-out check says worse: the operator confirms
                r = http.put(
                    f"/wells/{well}/model", json=body | {"confirm_worse": True}, headers=AUTH
                )
            r.raise_for_status()
            holdouts[well] = r.json()["holdout"]
        part = frame[(frame.time >= _ts(MID)) & (frame.time < _ts(MID) + pd.Timedelta(days=45))]
        replay_frame(part, bus=bus, progress=False, idle_timeout=2.0)
        for well, (change, _) in changes.items():
            view = http.get(f"/wells/{well}").json()
            trial = view["trial"]
            out.append(
                {
                    "change": f"{well} {change}",
                    "holdout": (holdouts[well].get("before"), holdouts[well].get("after")),
                    "confirmed": asked[well],
                    "n": trial["n"],
                    "mape": trial["mape"],
                    "shadow_mape": trial["shadow_mape"],
                    "p": trial.get("p_value"),
                    "outcome": trial["outcome"],
                    "now": f"{view['model']} {view['method']}",
                }
            )
    return out


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="31,32,33,34", help="eroding fields' seeds")
    ap.add_argument("--rate", type=float, default=0.3, help="the erosion rate of those fields")
    ap.add_argument("--methods", default="ol,bayes")
    ap.add_argument("--clean", default="41,42,43,44", help="clean fields' seeds (ol); '' for none")
    ap.add_argument("--wrong", default="", help="the wrong method of the two-well case; '' none")
    ap.add_argument("--wrong-seeds", default="51,52,53,54,55", help="its eroding fields' seeds")
    ap.add_argument("--wrong-clean", default="61,62,63,64", help="its clean fields' seeds")
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    cases = [
        (int(s), [f"erosion:rate={args.rate}"], m)
        for s in args.seeds.split(",")
        if s
        for m in args.methods.split(",")
    ]
    cases += [(int(s), [], "ol") for s in args.clean.split(",") if s]
    rate = [f"erosion:rate={args.rate}"]
    pairs = [(int(s), rate) for s in args.wrong_seeds.split(",") if s and args.wrong]
    pairs += [(int(s), []) for s in args.wrong_clean.split(",") if s and args.wrong]
    print(f"{'field':<26} {'method':<6} {'change':<13} {'held-out %':>13} {'n':>4} "
          f"{'MAPE %':>7} {'shadow %':>8} {'p':>9}  outcome")  # fmt: skip
    tally: dict[tuple[str, str, str], list[str]] = {}
    runs = [(seed, hidden, method, None) for seed, hidden, method in cases]
    runs += [(seed, hidden, "ol", args.wrong) for seed, hidden in pairs]
    with tempfile.TemporaryDirectory() as tmp:
        for i, (seed, hidden, method, wrong) in enumerate(runs):
            folder = Path(tmp) / str(i)
            folder.mkdir()
            started = time.perf_counter()
            if wrong is None:
                trials = run_case(seed, hidden, method, folder)
            else:
                trials = run_pair(seed, hidden, wrong, folder)
            name = f"{hidden[0] if hidden else 'clean'} seed {seed}"
            for t in trials:
                before, after = t["holdout"]
                p = "-" if t["p"] is None else f"{t['p']:.2g}"
                print(
                    f"{name:<26} {method:<6} {t['change']:<13} {_fmt(before):>6}/{_fmt(after):<6} "
                    f"{t['n']:>4} {_fmt(t['mape']):>7} {_fmt(t['shadow_mape']):>8} {p:>9}  "
                    f"{t['outcome']}{' (confirmed)' if t['confirmed'] else ''}"
                    + (f", now {t['now']}" if "now" in t else "")
                )
                kind = "eroding" if hidden else "clean"
                tally.setdefault((kind, method, t["change"].split()[-1]), []).append(t["outcome"])
            print(f"  ({time.perf_counter() - started:.0f} s)", flush=True)
    print("\nSummary (outcomes per field kind, method and change):")
    for (kind, method, change), outcomes in sorted(tally.items()):
        counts = {o: outcomes.count(o) for o in sorted(set(outcomes))}
        print(f"  {kind:<8} {method:<6} {change:<13} {json.dumps(counts)}")


if __name__ == "__main__":
    main()
