"""Benchmark: false alarms and detection delays of the residual alarm against the T^2 input test.

Prints a table; asserts nothing. For each field (simulated, seeds and sizes that the tests
do not use), model and method it runs the prequential study
(:func:`vfm_core.jobs.study.run_prequential`: predict, then learn, in time order, as the
service does) from ``--split-years`` after the field's start, feeds the predictions to the
residual alarm (:func:`vfm_core.residual_alarm.alarms_from_predictions`, the service's
defaults) and the inputs of the same measurements to the service's T^2 input test
(:class:`vfm_core.hotelling.StreamingHotelling` with ``drift.*`` defaults, its reference the
well's last measured inputs before the split, reset after each confirmed drift as the
service does), and reports:

- ``alarms/well-yr``: alarm onsets per well-year of tested data (residual alarm), beside
  ``T2/well-yr`` (confirmed input drifts). Goal on fields without a change: at most 1.
- for ``erosion:...:step=S`` fields (a sand event, a C_D step of S at a time the truth
  records per well): the wells whose event lies in the tested span at least 30 days after
  the split, how many had a residual alarm within 30 and within 180 days after the event
  (at the clean fields' rate of about 0.4 alarms per well-year an unrelated alarm falls
  within 30 days about 3 % of the time, within 180 days about 18 %), and the median delay
  (days, event to the first alarm within 180 days);
- for ``erosion;onset=event`` fields (wear that begins at the sand event, with or
  without a step): the same counts, from the event;
- for ``mpfm_bias;onset=event`` fields (a meter that starts to read off: its bias steps
  and its drift begins at a time the truth records per well, ``meter_event``): the same
  counts for the residual alarm, and beside them for the service's MPFM-against-well-test
  band (:func:`vfm_core.meter_check.mpfm_checks`: a well test the MPFM's median within
  24 h differs from by more than 10 %), which needs no model;
- for ``erosion`` (slow wear from the start) and ``mpfm_bias`` (a meter biased from the
  start and drifting away from the well tests): the share of wells with an alarm and the
  median day of the first one after the split (these changes have no onset inside the
  tested span: the time is from the split).

``--scales mad,winsorised`` runs the detector with each reference scale
(:data:`vfm_core.residual_alarm.SCALES`) on the same predictions, one row each: the rule
before and after, side by side. ``--accepts 0,30`` likewise runs the detector with each
``accept_periods`` (0: an alarm lasts until its level comes back, the rule before s46; 30:
an alarm still active after 30 periods closes as an accepted new level and the reference
restarts from them); the ``closed`` column counts the alarms closed as accepted. A value
ending in ``r`` (``30r``) keeps s46's rule after an accepted alarm (``alarm_on_return``:
a return toward the level before it may raise an alarm); without it, s47's quiet way back.

``--iid N`` instead runs the detector on N i.i.d. N(0, 1) periods (three seeds) and prints
the in-control run length against the design ``--arl0``.

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_alarms.py [--fields none:41:6:4,...]
        [--models mm,ham] [--methods ol,bayes] [--split-years 1] [--arl0 1000]
        [--physics sachdeva|bernoulli|gilbert] [--scales winsorised,mad] [--accepts 0,30]
        [--markdown docs/benchmarks/generated/alarms.md]

A field is ``hidden:seed:wells:years`` (hidden as ``vfm simulate --hidden``, ``+`` between
several effects and ``;`` instead of ``:`` inside one, e.g. ``erosion;step=0.1:44:6:4``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import shlex
import sys
import time

import numpy as np
import pandas as pd

from service.config import DriftSettings
from vfm_core import meter_check
from vfm_core.hotelling import StreamingHotelling
from vfm_core.jobs.study import run_prequential
from vfm_core.meter_check import SAME_Z, SHIFT_Z, mpfm_checks
from vfm_core.observations import validate_frame
from vfm_core.residual_alarm import ResidualCusum, alarms_from_predictions, cusum_threshold
from vfm_core.schema import INPUT_COLUMNS, SOURCE, TARGET, TIME, WELL
from vfm_core.simulate import simulate_field

DEFAULT_FIELDS = (
    "none:41:6:4",
    "none:42:4:5",
    "none:43:8:3",
    "erosion;step=0.1:44:6:4",
    "erosion;rate=0;step=0.1:47:8:4",
    "erosion:45:6:4",
    "mpfm_bias:46:6:4",
)
DAY = pd.Timedelta(days=1)


def parse_field(text: str) -> tuple[list[str], int, int, float]:
    hidden, seed, wells, years = text.split(":")
    effects = [] if hidden == "none" else [h.replace(";", ":") for h in hidden.split("+")]
    return effects, int(seed), int(wells), float(years)


def t2_drifts(frame: pd.DataFrame, split: pd.Timestamp) -> int:
    """Confirmed input drifts of the service's T^2 test over the tested span, all wells."""
    d = DriftSettings()
    target = frame[SOURCE].isin(["mpfm", "well_test"]) & frame[TARGET].notna()
    total = 0
    for _, g in frame[target].groupby(WELL):
        x = g[list(INPUT_COLUMNS)].to_numpy(dtype=float)
        before = (g[TIME] < split).to_numpy()
        det = StreamingHotelling(d.reference_size, d.alpha, d.confirm)
        seen = list(x[before][-d.reference_size :])
        if len(seen) >= d.reference_size:
            det.reset(np.asarray(seen))
        for row in x[~before]:
            was = det.drift_detected
            det.update(row)
            seen = (seen + [row])[-d.reference_size :]
            if det.drift_detected and not was:
                total += 1
                det.reset(np.asarray(seen) if len(seen) >= d.reference_size else None)
    return total


def well_years(predictions: pd.DataFrame) -> float:
    span = predictions.groupby("well")["time"].agg(["min", "max"])
    return float(((span["max"] - span["min"]) / DAY).sum() / 365.25)


def event_delays(
    alarms: list[dict], truth: dict, split: pd.Timestamp, last: pd.Timestamp, key: str
):
    """Per well whose event ``key`` (the truth's ``sand_event`` or ``meter_event``) lies at
    least 30 days after the split and 180 days before ``last``: whether an alarm started
    within 30 and within 180 days after it, and the delays (days) of those within 180."""
    tested, found, soon, delays = 0, 0, 0, []
    for well, info in truth["wells"].items():
        if key not in info:
            continue
        event = pd.Timestamp(info[key])
        event = event.tz_localize("UTC") if event.tzinfo is None else event.tz_convert("UTC")
        if event < split + 30 * DAY or event > last - 180 * DAY:
            continue
        tested += 1
        after = [a["start"] for a in alarms if a["well"] == well and a["start"] >= event]
        after = [t for t in after if t <= event + 180 * DAY]
        if after:
            found += 1
            delays.append((min(after) - event) / DAY)
            soon += delays[-1] <= 30
    return tested, found, soon, delays


def _event_note(what: str, found: tuple[int, int, int, list[float]]) -> str:
    tested, hit, soon, delays = found
    med = f"{np.median(delays):.0f} d" if delays else "-"
    return (
        f"{what}: {soon}/{tested} wells within 30 d, {hit}/{tested} within 180 d, "
        f"median delay {med}"
    )


def which_moved(
    alarms: list[dict], checks: pd.DataFrame, truth: dict, key: str, last: pd.Timestamp
) -> str:
    """For each well whose event ``key`` had a residual alarm on the MPFM stream within 180
    days (event before ``last`` - 180 days), the first well test compared with the MPFM
    after that alarm began (within 180 days of the event), read as the service's
    ``which_moved`` reads it (:func:`vfm_core.meter_check.which_moved`, with the alarm's
    size at its raise): ``meter``, ``unclear`` or ``well``, counted; beside it in brackets
    the z alone (the rule before s51: ``meter`` |z| > 3, ``well`` |z| < 1). A meter event
    should say ``meter``, a well that changed ``well``. Then the same with every well test
    compared from the alarm's start to 180 days after the event read together (``which_moved``
    with ``pairs``, s54: the service's reading at the last of them), each set against the
    pairs from before the alarm."""
    said = {"meter": 0, "unclear": 0, "well": 0}
    alone = dict(said)
    pooled = dict(said)
    n_pooled: list[int] = []
    for well, info in truth["wells"].items():
        if key not in info:
            continue
        event = pd.Timestamp(info[key])
        if event > last - 180 * DAY:
            continue
        found = [
            a
            for a in alarms
            if a["well"] == well
            and a["source"] == "mpfm"
            and event <= a["start"] <= event + 180 * DAY
        ]
        if not found:
            continue
        first = min(found, key=lambda a: a["start"])
        c = checks[(checks["well"] == well) & (checks["time"] >= first["start"])]
        c = c[(c["time"] <= event + 180 * DAY) & c["shifted"].notna()]
        if len(c):
            row = c.iloc[0]
            alarm = {"source": "mpfm", "since": first["start"].isoformat(), "shift": first["shift"]}
            check = {**row.to_dict(), "well_test_time": row["time"].isoformat()}
            said[meter_check.which_moved(alarm, check)["moved"]] += 1
            z = abs(float(row["z"]))
            alone["meter" if z > SHIFT_Z else "well" if z < SAME_Z else "unclear"] += 1
            # all of them, each against the first one's usual (the pairs before the alarm)
            pairs = [
                (t.value, float(r))
                for t, r in zip(c["time"], c["relative_difference"], strict=True)
            ]
            latest = {**check, "well_test_time": c["time"].iloc[-1].isoformat()}
            latest["relative_difference"] = pairs[-1][1]
            latest["z"] = (
                math.log1p(pairs[-1][1]) - math.log1p(float(row["usual_difference"]))
            ) / float(row["usual_spread"])
            together = meter_check.which_moved(alarm, latest, pairs)
            pooled[together["moved"]] += 1
            n_pooled.append(together["n_well_tests"])
    counts = ", ".join(f"{k} {v} ({alone[k]})" for k, v in said.items())
    out = "first well test after the MPFM alarm (z alone): " + counts
    if n_pooled:
        out += f"; all within 180 d read together ({min(n_pooled)}-{max(n_pooled)} well tests): "
        out += ", ".join(f"{k} {v}" for k, v in pooled.items())
    return out


def band_alarms(frame: pd.DataFrame) -> list[dict]:
    """The service's MPFM-against-well-test band (:func:`vfm_core.meter_check.mpfm_checks`,
    its defaults) as alarm starts: every well test the MPFM disagrees with."""
    checks = mpfm_checks(frame)
    off = checks[~checks["agrees"].astype(bool)]
    return [{"well": w, "start": t} for w, t in zip(off["well"], off["time"], strict=True)]


def first_alarms(alarms: list[dict], wells: list[str], split: pd.Timestamp):
    firsts = []
    for w in wells:
        starts = [a["start"] for a in alarms if a["well"] == w]
        if starts:
            firsts.append((min(starts) - split) / DAY)
    return firsts


def describe(
    alarms: list[dict],
    effects: list[str],
    truth: dict,
    split: pd.Timestamp,
    p: pd.DataFrame,
    frame: pd.DataFrame,
) -> tuple[str, str]:
    """The change column (sand-event or meter-event detections and delays, or the first
    alarms of a field that changes from the start) and the alarms counted by meter and
    direction."""
    note = ""
    last = p["time"].max()
    if any(e.startswith("erosion") and ("step" in e or "onset=event" in e) for e in effects):
        found = event_delays(alarms, truth, split, last, "sand_event")
        step = any(e.startswith("erosion") and "step" in e for e in effects)
        note = _event_note("sand event" if step else "wear onset", found)
        note += "; " + which_moved(alarms, mpfm_checks(frame), truth, "sand_event", last)
    elif any(e.startswith("mpfm_bias") and "onset=event" in e for e in effects):
        note = _event_note("meter event", event_delays(alarms, truth, split, last, "meter_event"))
        band = event_delays(band_alarms(frame), truth, split, last, "meter_event")
        note += "; " + _event_note("MPFM band", band)
        note += "; " + which_moved(alarms, mpfm_checks(frame), truth, "meter_event", last)
    elif effects:
        firsts = first_alarms(alarms, sorted(p["well"].unique()), split)
        med = f"{np.median(firsts):.0f} d after split" if firsts else "-"
        note = f"{len(firsts)}/{p['well'].nunique()} wells alarmed, first: {med}"
    else:
        tested = [a for a in band_alarms(frame) if a["start"] >= split]
        note = f"MPFM band: {len(tested)} well tests off by more than 10 %"
    streams: dict[str, int] = {}
    for a in alarms:
        key = f"{a['source']}:{a['direction']}"
        streams[key] = streams.get(key, 0) + 1
    # how many of them are small: their shift at the raise under the meter's usual error
    # before it (vfm_core.residual_alarm.alarm_size; shown in the warning colour, alerted
    # at severity info)
    small = sum(a.get("small") is True for a in alarms)
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(streams.items()))
    return note, kinds + (f"; small {small}" if alarms else "")


def _accept(spec: str) -> tuple[int, bool]:
    """``30`` -> (30, False); ``30r`` -> (30, True): accept_periods and alarm_on_return."""
    return int(spec.rstrip("r")), spec.endswith("r")


def iid_run_length(arl0: float, n: int, scale: str = "winsorised", accept: str = "0") -> None:
    """The detector as built (scale estimated, not known) on i.i.d. N(0, 1) residuals, one
    per period: periods per false alarm against the design."""
    print(
        f"design arl0 = {arl0:g} periods, h = {cusum_threshold(arl0):.3f}, scale {scale}, "
        f"accept_periods {accept}"
    )
    for seed in range(3):
        periods, on_return = _accept(accept)
        det = ResidualCusum(
            arl0=arl0,
            period_s=0.0,
            scale=scale,
            accept_periods=periods,
            alarm_on_return=on_return,
        )
        x = np.random.default_rng(seed).standard_normal(n)
        for i, v in enumerate(x):
            det.update(float(v), i)
        alarms = len(det.events)
        rl = (n - det.min_periods) / alarms if alarms else float("inf")
        print(f"seed {seed}: {alarms} alarms in {n} periods, {rl:.0f} periods per alarm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fields", default=",".join(DEFAULT_FIELDS))
    ap.add_argument("--models", default="mm,ham")
    ap.add_argument("--methods", default="ol,bayes")
    ap.add_argument("--split-years", type=float, default=1.0)
    ap.add_argument(
        "--physics",
        default="sachdeva",
        help="the simulator's truth (vfm simulate --physics): a second physics puts the "
        "models' own choke law out of the truth, so a 'clean' field has a misfit the learner "
        "follows",
    )
    ap.add_argument(
        "--arl0", type=float, default=1000.0, help="target in-control run length, periods"
    )
    ap.add_argument(
        "--scales",
        default="winsorised",
        help="reference scales to compare on the same predictions (comma-separated: "
        "winsorised, mad)",
    )
    ap.add_argument(
        "--accepts",
        default="30",
        help="accept_periods to compare on the same predictions (comma-separated; 0: never; "
        "a trailing r, e.g. 30r: a return toward the level before an accepted alarm may "
        "raise one, the rule of s46)",
    )
    ap.add_argument("--markdown", help="also write the table as Markdown to this file")
    ap.add_argument(
        "--iid",
        type=int,
        default=0,
        help="instead: the in-control run length on this many i.i.d. N(0, 1) periods, 3 seeds",
    )
    args = ap.parse_args()
    if args.iid:
        for scale, accept in itertools.product(args.scales.split(","), args.accepts.split(",")):
            iid_run_length(args.arl0, args.iid, scale, accept)
        return
    rows: list[str] = []
    header = (
        f"{'field':<26} {'model':<5} {'method':<6} {'scale':<10} {'accept':>6} {'well-yr':>7} "
        f"{'alarms':>6} {'accepted':>8} "
        f"{'alarms/well-yr':>14} {'T2':>5} {'T2/well-yr':>10}  change detected"
    )
    print(header)
    print("-" * len(header))
    for text in args.fields.split(","):
        effects, seed, n_wells, years = parse_field(text)
        sim = simulate_field(
            wells=n_wells, years=years, seed=seed, hidden=effects, physics=args.physics
        )
        frame = validate_frame(sim.observations).frame
        start = pd.Timestamp(sim.truth["start"])
        start = start.tz_localize("UTC") if start.tzinfo is None else start.tz_convert("UTC")
        split = start + pd.Timedelta(days=365.25 * args.split_years)
        t2 = t2_drifts(frame, split)
        for model in args.models.split(","):
            for method in args.methods.split(","):
                started = time.perf_counter()
                run = run_prequential(frame, model, method, split=split)
                p = run.predictions[np.isfinite(run.predictions["predicted"])]
                wy = well_years(p)
                for scale, accept in itertools.product(
                    args.scales.split(","), args.accepts.split(",")
                ):
                    periods, on_return = _accept(accept)
                    alarms = alarms_from_predictions(
                        p,
                        arl0=args.arl0,
                        scale=scale,
                        accept_periods=periods,
                        alarm_on_return=on_return,
                    )
                    note, kinds = describe(alarms, effects, sim.truth, split, p, frame)
                    acc = sum(a["closed"] == "accepted" for a in alarms)
                    rows.append(
                        f"| `{text}` | {model} | {method} | {scale} | {accept} | {wy:.1f} | "
                        f"{len(alarms)} | {acc} | {len(alarms) / wy:.2f} | {t2} | "
                        f"{t2 / wy:.2f} | {note or '-'} | {kinds} |"
                    )
                    print(
                        f"{text:<26} {model:<5} {method:<6} {scale:<10} {accept:>6} {wy:7.1f} "
                        f"{len(alarms):6d} {acc:8d} {len(alarms) / wy:14.2f} {t2:5d} "
                        f"{t2 / wy:10.2f}  {note} [{kinds}]  "
                        f"({time.perf_counter() - started:.0f} s)",
                        flush=True,
                    )
    if args.markdown:
        command = shlex.join(["python", "benchmarks/bench_alarms.py", *sys.argv[1:]])
        with open(args.markdown, "w", encoding="utf-8") as out:
            out.write(
                f"Made by `{command}`.\n\n"
                "| field | model | method | scale | accept | well-yr | alarms | accepted | "
                "alarms/well-yr | T2 drifts | T2/well-yr | change | alarms by meter:direction |\n"
                "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|\n"
                + "\n".join(rows)
                + "\n"
            )


if __name__ == "__main__":
    main()
