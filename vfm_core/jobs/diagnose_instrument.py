"""The diagnosis's ``instrument`` verdict: when the evidence points to one input's fault.

A drifting or offset transmitter makes the model's rate wrong in a way that a physical
effect can partly "explain" (a drifting ``p_down`` looks like a driver in p_down or a
critical-ratio effect). :mod:`vfm_core.sensor_faults` detects faults per input and well
(``frozen``, ``spike``, ``drift``, ``offset``, ``out_of_range``); this module decides when a
diagnosis's verdict for a well is that fault rather than physics (:func:`instrument_verdicts`).

The rule, for a well whose verdict names something (``effect``, ``driver`` or ``carried``)
and that has a detected fault of a kind that biases the rate for as long as it lasts
(:data:`INSTRUMENT_KINDS`; a spike is one sample; and a choke offset, found by the measured
rate: :data:`INSTRUMENT_FAULTS`) overlapping the scored period:

* **the residual coincides**: the verdict's gain (the paired per-measurement differences of
  absolute percentage error, the verdict's candidate less the baseline, replayed with the
  well's method) is larger inside the fault's interval than outside it beyond chance: a
  one-sided Welch t-test of the means of :data:`BLOCK_DAYS`-day blocks inside against those
  outside, at :data:`ALPHA` divided by the well's number of such faults (Bonferroni).
  Physics acts over the whole history; a transmitter fault only while it lasts. A detected
  fault alone is not enough: the detector's offsets have false alarms (a process that
  steps), and a fault that does not carry the verdict's evidence is not its cause;
* **the driver coincides**: when the verdict's driver (the variable of its correction, or
  of the evidence that named its effect) is one the faulty input enters
  (:data:`SENSOR_VARIABLES`: p_down enters p_down and p_down/p_up), that fault was the
  suspect before the test looked: it is tested at :data:`ALPHA` itself, not divided. A
  driver match alone is not enough: a false offset of the detector in a well whose
  residual truly depends on p_down would otherwise turn physics into an instrument half
  the time.

The well's verdict is then ``instrument``: the sensor, the fault's kind, its interval and
the detector's evidence, with the verdict it replaces (``instead_of``). The field's verdict
is ``instrument`` when more than half of its candidate's live gain (per-well changes times
their measurements) comes from wells whose verdict is ``instrument``: the field's evidence
then points to those inputs, not to physics. Nothing is offered for an ``instrument``
verdict: fix or recalibrate the transmitter (the service pauses learning while a fault is
active; see ``docs/guide/sensor-faults.md``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

from vfm_core.schema import TIME, WELL
from vfm_core.sensor_faults import SENSORS, faults_of_frame

__all__ = [
    "INSTRUMENT_KINDS",
    "INSTRUMENT_FAULTS",
    "SENSOR_VARIABLES",
    "ALPHA",
    "BLOCK_DAYS",
    "input_faults",
    "fault_coincides",
    "instrument_verdicts",
]

#: Fault kinds that bias the rate model for as long as they last (a spike is one sample)
#: and whose false rate is within the detectors' budget: an input's offset (0.22 false per
#: well-year on clean fields before the p_down steps of no consequence and those the rate
#: followed were set aside, 0.04-0.06 after: benchmarks/bench_sensor_faults.py) raises no
#: alarm on the page or in VfmSensorFault, and names no instrument here either (a false one
#: replaced a right ``effect erosion`` on a clean-instrument field)
INSTRUMENT_KINDS = ("frozen", "drift", "out_of_range")
#: (sensor, kind) pairs that name an instrument besides those kinds: a choke offset, found
#: by its witness (the MPFM's rate does not follow a move of the reading,
#: vfm_core.rate_witness), whose false rate is within the detectors' budget
INSTRUMENT_FAULTS = (("choke", "offset"),)
#: The variables each input's reading enters (the diagnosis's drivers).
SENSOR_VARIABLES: dict[str, tuple[str, ...]] = {
    "choke": ("choke",),
    "p_up": ("p_up", "p_ratio"),
    "p_down": ("p_down", "p_ratio"),
    "t_up": ("t_up",),
    "eta_gas": ("eta_gas",),
    "eta_oil": ("eta_oil", "water_cut"),
}
#: The level of the residual-coincidence test (before the Bonferroni division).
ALPHA = 0.05
#: Block length of the coincidence test, days: a week holds a few measurements a well and
#: keeps enough blocks inside a fault of a month.
BLOCK_DAYS = 7.0
#: Fewest measurements inside and outside a fault's interval for the test.
MIN_ROWS = 10


def input_faults(frame: pd.DataFrame) -> list[dict[str, Any]]:
    """The faults :mod:`vfm_core.sensor_faults` detects in ``frame``'s inputs, every well
    in time order as the service would (dicts with ``well``, ``sensor``, ``kind``,
    ``start``, ``end``, ``evidence``, ``detected``); the MPFM's rates (``source``,
    ``q_total``) feed the choke-rate witness where the frame has them."""
    cols = [TIME, WELL, *SENSORS]
    if any(c not in frame.columns for c in cols):
        return []
    rates = [c for c in ("source", "q_total") if c in frame.columns]
    return faults_of_frame(frame[cols + rates])


def _utc(x: Any) -> pd.Timestamp:
    t = pd.Timestamp(x)
    return t.tz_localize("UTC") if t.tzinfo is None else t.tz_convert("UTC")


def _names_instrument(fault: Mapping[str, Any]) -> bool:
    """True for a fault that may name an instrument: its kind is one of
    :data:`INSTRUMENT_KINDS`, or its sensor and kind one of :data:`INSTRUMENT_FAULTS`."""
    kind = fault.get("kind")
    return kind in INSTRUMENT_KINDS or (fault.get("sensor"), kind) in INSTRUMENT_FAULTS


def _interval(fault: Mapping[str, Any], last: pd.Timestamp) -> tuple[pd.Timestamp, pd.Timestamp]:
    start = _utc(fault["start"])
    end = _utc(fault["end"]) if fault.get("end") else _utc(last)
    return start, end


def fault_coincides(
    pairs: pd.DataFrame, start: pd.Timestamp, end: pd.Timestamp, alpha: float = ALPHA
) -> dict[str, Any]:
    """Whether the gain in ``pairs`` (one well's paired differences, columns ``time`` and
    ``d`` in points: candidate less baseline, negative where the candidate helps) is larger
    inside [start, end] than outside, beyond chance: a one-sided Welch t-test of the
    :data:`BLOCK_DAYS`-day block means. Returns ``inside``, ``outside`` (mean d, points),
    ``n_inside``, ``n_outside`` (rows), ``p_value`` and ``coincides``."""
    t = pd.DatetimeIndex(pd.to_datetime(pairs["time"], utc=True))
    start, end = _utc(start), _utc(end)
    d = pairs["d"].to_numpy(dtype=float)
    inside = np.asarray((t >= start) & (t <= end), dtype=bool)
    out: dict[str, Any] = {
        "inside": float(np.mean(d[inside])) if inside.any() else None,
        "outside": float(np.mean(d[~inside])) if (~inside).any() else None,
        "n_inside": int(inside.sum()),
        "n_outside": int((~inside).sum()),
        "p_value": 1.0,
        "coincides": False,
    }
    if inside.sum() < MIN_ROWS or (~inside).sum() < MIN_ROWS:
        return out
    step = int(BLOCK_DAYS * 86400e9)
    k = (t.as_unit("ns").asi8 - int(t.as_unit("ns").asi8.min())) // step
    frame = pd.DataFrame({"k": k, "in": inside, "d": d})
    means = frame.groupby(["in", "k"])["d"].mean()
    a = means.loc[True].to_numpy(dtype=float) if True in means.index.levels[0] else np.array([])
    b = means.loc[False].to_numpy(dtype=float) if False in means.index.levels[0] else np.array([])
    if len(a) < 2 or len(b) < 2:
        return out
    from scipy.stats import ttest_ind

    res = ttest_ind(a, b, equal_var=False, alternative="less")
    p = float(res.pvalue) if math.isfinite(float(res.pvalue)) else 1.0
    out["p_value"] = p
    out["coincides"] = bool(p < alpha)
    return out


def _verdict_driver(verdict: Mapping[str, Any]) -> str | None:
    return verdict.get("driver")


def instrument_verdicts(
    verdicts: dict[str, dict[str, Any]],
    faults: Sequence[Mapping[str, Any]],
    pairs_of: Callable[[dict[str, Any], str | None], pd.DataFrame | None],
    gains_of: Callable[[dict[str, Any]], dict[str, float]],
    split: pd.Timestamp,
    last: pd.Timestamp,
) -> list[str]:
    """Turn the verdicts whose evidence points to one input's fault into ``instrument``
    verdicts, in place (see the module docstring); returns the wells turned.

    ``verdicts``: ``{"field": ..., well: ...}`` (each a verdict dict with ``kind``,
    ``effect``, ``driver``, ``text``; a single well's diagnosis may hold the same dict under
    both keys). ``faults``: :func:`input_faults`. ``pairs_of(verdict, well)``: the paired
    live differences of the verdict's candidate against the baseline for ``well`` (None when
    the candidate was not replayed). ``gains_of(verdict)``: each well's live change times its
    measurements (points x rows; negative is a gain). ``split``: where the scored period
    starts; ``last``: the end of the data (an open fault lasts until it)."""
    wells = [w for w in verdicts if w != "field"] or ["field"]
    single = len(wells) == 1
    turned: list[str] = []
    for w in wells:
        v = verdicts[w]
        if v.get("kind") not in ("effect", "driver", "carried"):
            continue
        name = None if w == "field" else w
        mine = [
            f
            for f in faults
            if _names_instrument(f)
            and (single or str(f.get("well")) == w)
            and _interval(f, last)[1] >= _utc(split)
        ]
        if not mine:
            continue
        pairs = pairs_of(v, name)
        if pairs is None or pairs.empty:
            continue
        found = None
        driver = _verdict_driver(v)
        for f in mine:
            start, end = _interval(f, last)
            by_driver = driver is not None and driver in SENSOR_VARIABLES.get(str(f["sensor"]), ())
            level = ALPHA if by_driver else ALPHA / len(mine)
            test = fault_coincides(pairs, max(start, _utc(split)), end, level)
            if test["coincides"]:
                found = (f, test, "driver and residual" if by_driver else "residual")
                break
        if found is None:
            continue
        f, test, how = found
        new = _instrument(v, f, test, how, name)
        verdicts[w] = new
        if single:
            verdicts["field"] = new
        turned.append(w)
    if single or not turned:
        return turned
    field = verdicts["field"]
    if field.get("kind") not in ("effect", "driver", "carried"):
        return turned
    gains = gains_of(field)
    total = sum(g for g in gains.values() if math.isfinite(g))
    from_faulty = sum(g for w, g in gains.items() if w in turned and math.isfinite(g))
    if total < 0 and from_faulty <= 0.5 * total:  # both negative: more than half the gain
        first = verdicts[turned[0]]["instrument"]
        share = from_faulty / total
        new = dict(verdicts[turned[0]])
        new["instead_of"] = {k: field.get(k) for k in ("kind", "effect", "driver", "text")}
        new["instrument_wells"] = list(turned)
        new["text"] = (
            f"An instrument, not physics: {100 * share:.0f} % of the field's evidence for "
            f"{_named(field)} comes from {', '.join(turned)}, whose {first['sensor']} "
            f"transmitter is faulty ({first['kind']} from {first['start']}); the evidence "
            "points to that input. Fix or recalibrate it before adding any effect; "
            f"the verdict without this check: {field.get('text', '')}"
        )
        verdicts["field"] = new
    return turned


def _named(v: Mapping[str, Any]) -> str:
    return str(v.get("effect") or (f"a correction in {v['driver']}" if v.get("driver") else "it"))


def _instrument(
    v: Mapping[str, Any],
    fault: Mapping[str, Any],
    test: Mapping[str, Any],
    how: str,
    well: str | None,
) -> dict[str, Any]:
    who = "" if well is None else f" of {well}"
    interval = f"from {fault['start']}" + (f" to {fault['end']}" if fault.get("end") else " on")
    why = (
        f"the verdict's gain is concentrated in the fault's interval ({test['inside']:+.2f} "
        f"points a measurement inside, {test['outside']:+.2f} outside; p = "
        f"{test['p_value']:.2g}, Welch's test of weekly means)"
    )
    if how != "residual":
        why += f", and the residual's driver {v.get('driver')} is what that reading enters"
    text = (
        f"An instrument, not physics: the {fault['sensor']} transmitter{who} is faulty "
        f"({fault['kind']}, {interval}; {fault.get('evidence', '')}), and {why}. What the "
        f"diagnosis would otherwise name ({_named(v)}) is that fault's trace: fix or "
        "recalibrate the transmitter before adding any effect."
    )
    return {
        "kind": "instrument",
        "effect": None,
        "driver": None,
        "text": text,
        "instrument": {
            "sensor": fault["sensor"],
            "kind": fault["kind"],
            "start": fault["start"],
            "end": fault.get("end"),
            "evidence": fault.get("evidence", ""),
            "coincides": how,
            "test": dict(test),
        },
        "instead_of": {k: v.get(k) for k in ("kind", "effect", "driver", "text")},
        "live": v.get("live"),
        "outage": v.get("outage"),
        "evidence": v.get("evidence", []),
        "offer": False,
        "reason": "instrument",
    }
