"""Is the diagnosis's verdict right? Fields with a known cause, the well's model and method.

For each case, physics and seed a field is simulated (``vfm simulate``), diagnosed as the
service diagnoses a well (the well's model and learning method replayed from the split, its
pool of wells beside it; the default candidates and settings, nothing tuned here), and the
field's verdict and every well's own verdict are checked against the cause put in:

* ``none``: a field without a hidden effect; right is ``noise`` (for the field and for each
  well), or a verdict (``effect`` or ``carried``) naming physics that the truth has and the
  diagnosed model's Sachdeva core lacks (:data:`BACKGROUND`: on the Sachdeva truth nothing;
  on the Bernoulli truth Simpson's slip multiplier, its real gas and its critical ratio).
* ``erosion``, ``valve``, ``real_gas``: the simulator's hidden effect; right is a verdict
  (``effect``, or ``carried`` when the learner already follows it) naming that physics
  (erosion or erosion_time; any valve family; real_gas).
* ``tempcd``: a discharge coefficient that grows 6.8 % per 10 K of upstream temperature, an
  effect outside the library; right is ``driver`` t_up (or ``carried`` naming t_up: the
  correction found, the learner already following it).

``--physics`` takes the simulator's truths (``sachdeva``, and the second physics of
``vfm simulate --physics``); on a physics without an effect the case is skipped with a note.
What is right depends on the truth only through :data:`BACKGROUND` (see
``docs/benchmarks/verdicts.md`` for why each entry is there).
Each line also gives the field verdict's trial forecast (``trial``: the change as the service
applies it, backtested over the last 30 days of data). Prints one line per diagnosis and a summary; ``--markdown PATH`` writes the table. Run:

    python benchmarks/bench_verdicts.py [--cases none,erosion,valve,real_gas,tempcd]
        [--combos mm:ol,mm:bayes,ham:ol] [--seeds 61,62] [--physics sachdeva]
        [--wells 4] [--years 3] [--split 2017-07-01] [--until DATE] [--markdown PATH]

``--until`` diagnoses the data before that date only: what a live service's store holds
when an operator diagnoses a well months into the replay.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from vfm_core.errors import ConfigError
from vfm_core.jobs.diagnose import run_diagnosis
from vfm_core.simulate import simulate_field

EXPECTED = {
    "none": "noise",
    "erosion": "erosion",
    "valve": "valve",
    "real_gas": "real_gas",
    "tempcd": "driver (or carried) t_up",
}
#: Per truth physics, the library effects that name what the truth has and the diagnosed
#: model's core (Sachdeva's homogeneous, ideal-gas choke with a constant critical ratio:
#: ``mm``, and the core of ``ham``/``hem``) lacks, on a field without a hidden effect. A
#: verdict naming one of them (``effect`` or ``carried``) is physics the model misses, not a
#: false discovery. Sachdeva: none (the model is the truth). Bernoulli
#: (:mod:`vfm_core.sim_physics`): Simpson's two-phase slip multiplier (``slip``: the library's
#: effect is that multiplier), a Hall-Yarborough real gas (``real_gas``: Papay's Z for the
#: same compressibility) and an orifice law whose flow is flat below a fixed critical ratio
#: where Sachdeva's isentropic expansion is not (``critical_ratio``: the one library effect
#: that changes where and how the flow chokes). Gilbert: an empirical correlation that no
#: single library effect stands for; only ``noise`` counts.
BACKGROUND: dict[str, tuple[str, ...]] = {
    "sachdeva": (),
    "bernoulli": ("slip", "real_gas", "critical_ratio"),
    "gilbert": (),
}


def _field(case: str, physics: str, seed: int, wells: int, years: float) -> pd.DataFrame:
    hidden = [] if case in ("none", "tempcd") else [case]
    field = simulate_field(wells=wells, years=years, seed=seed, hidden=hidden, physics=physics)
    obs = field.observations.copy()
    if case == "tempcd":  # C_D(t_up): the true rate times 1 + 0.068 per 10 K above 60 degC
        obs["q_total"] = obs["q_total"] * (1.0 + 0.068 * (obs["t_up"].to_numpy() - 60.0) / 10.0)
    return obs


def expected(case: str, physics: str = "sachdeva") -> str:
    """The right verdicts of a case on a truth physics, in words (the table's header)."""
    lacks = BACKGROUND.get(physics, ())
    if case == "none" and lacks:
        return "noise or " + " / ".join(lacks)
    return EXPECTED[case]


def right(case: str, verdict: dict[str, Any], physics: str = "sachdeva") -> bool:
    """Whether a verdict ({kind, effect, driver}) names the cause put in, on ``physics``'s
    truth (a field without a hidden effect may be named by what :data:`BACKGROUND` says
    the model lacks under that truth)."""
    kind, effect = verdict.get("kind"), verdict.get("effect") or ""
    if case == "none":
        if kind == "noise":
            return True
        return kind in ("effect", "carried") and effect in BACKGROUND.get(physics, ())
    if case == "tempcd":
        return kind in ("driver", "carried") and verdict.get("driver") == "t_up"
    if kind not in ("effect", "carried"):
        return False
    if case == "erosion":
        return effect.startswith("erosion")
    if case == "valve":
        return effect.startswith("valve")
    return effect == case


def right_among(case: str, verdict: dict[str, Any], physics: str = "sachdeva") -> bool:
    """Whether the cause put in is among what the verdict names: its effect, or a rival the
    diagnosis says it cannot tell apart from it (``alternatives``) or finds at work beside it
    (``then``, the next step); a weaker score than :func:`right`, reported beside it."""
    others = [*(verdict.get("alternatives") or []), *(verdict.get("then") or [])]
    return right(case, verdict, physics) or any(
        right(case, {**verdict, "effect": o}, physics) for o in others
    )


def _label(v: dict[str, Any]) -> str:
    label = f"{v.get('kind')} {v.get('effect') or v.get('driver') or ''}".strip()
    if v.get("then"):
        label += " then " + ", ".join(v["then"])
    if v.get("alternatives"):
        label += " (or " + ", ".join(v["alternatives"]) + ")"
    return label


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default="none,erosion,valve,real_gas,tempcd")
    parser.add_argument("--combos", default="mm:ol,mm:bayes,ham:ol")
    parser.add_argument("--seeds", default="61")
    parser.add_argument("--physics", default="sachdeva")
    parser.add_argument("--wells", type=int, default=4)
    parser.add_argument("--years", type=float, default=3.0)
    parser.add_argument("--split", default="2017-07-01")
    parser.add_argument(
        "--until",
        default=None,
        help="diagnose the data before this date only (UTC): what a live store holds when "
        "an operator diagnoses a well months into the replay",
    )
    parser.add_argument("--markdown", default=None, help="write the table here (Markdown)")
    args = parser.parse_args()
    rows: list[dict[str, Any]] = []
    planned = (
        len(args.physics.split(","))
        * len(args.cases.split(","))
        * len(args.seeds.split(","))
        * len(args.combos.split(","))
    )
    print(
        f"{'physics':<9} {'case':<9} {'seed':>4} {'model':<5} {'method':<6} "
        f"{'field verdict':<26} {'field':>5} {'wells right':>11} {'live %':>7} {'d live':>7} "
        f"{'d trial':>7} {'time s':>6}"
    )
    for physics in args.physics.split(","):
        for case in args.cases.split(","):
            for seed in [int(s) for s in args.seeds.split(",")]:
                try:
                    obs = _field(case, physics, seed, args.wells, args.years)
                    if args.until:
                        obs = obs[obs["time"] < pd.Timestamp(args.until, tz="UTC")]
                except ConfigError as exc:
                    print(f"{physics:<9} {case:<9} {seed:>4} skipped: {exc}")
                    planned -= len(args.combos.split(","))
                    continue
                for combo in args.combos.split(","):
                    model, method = combo.split(":")
                    started = time.perf_counter()
                    diag = run_diagnosis(obs, model, method=method, split=args.split)
                    elapsed = time.perf_counter() - started
                    verdicts = diag.well_verdicts or {"field": {"kind": diag.verdict_kind}}
                    field_v = verdicts["field"]
                    wells = {w: v for w, v in verdicts.items() if w != "field"}
                    n_right = sum(right(case, v, physics) for v in wells.values())
                    live_change = ((field_v.get("live") or {}) or {}).get("change")
                    trial_change = ((field_v.get("trial") or {}) or {}).get("change")
                    row = {
                        "physics": physics,
                        "case": case,
                        "seed": seed,
                        "model": model,
                        "method": method,
                        "verdict": _label(field_v),
                        "right": right(case, field_v, physics),
                        "right_among": right_among(case, field_v, physics),
                        "wells_right_among": sum(
                            right_among(case, v, physics) for v in wells.values()
                        ),
                        "wells_right": n_right,
                        "wells": len(wells),
                        "wells_noise": sum(v.get("kind") == "noise" for v in wells.values()),
                        "live": diag.live.get("mape", float("nan")),
                        "change": np.nan if live_change is None else float(live_change),
                        "trial": np.nan if trial_change is None else float(trial_change),
                        "time_s": elapsed,
                        "well_verdicts": {w: _label(v) for w, v in wells.items()},
                        "proxies": ", ".join(field_v.get("trend_proxies") or []),
                    }
                    rows.append(row)
                    if args.markdown:
                        _write_markdown(args, rows, planned, final=False)
                    print(
                        f"{physics:<9} {case:<9} {seed:>4} {model:<5} {method:<6} "
                        f"{row['verdict']:<26} {'yes' if row['right'] else 'NO':>5} "
                        f"{n_right:>5}/{len(wells):<5} {row['live']:>7.2f} "
                        f"{row['change']:>+7.2f} {row['trial']:>+7.2f} {elapsed:>6.0f}"
                        + (
                            f"  (set aside as trend proxies: {row['proxies']})"
                            if row["proxies"]
                            else ""
                        ),
                        flush=True,
                    )
    if rows:
        print(_summary(rows))
    if args.markdown:
        _write_markdown(args, rows, planned, final=True)
        print(f"Wrote {args.markdown}.")


def _summary(rows: list[dict[str, Any]]) -> str:
    fields_right = sum(r["right"] for r in rows)
    wells_right = sum(r["wells_right"] for r in rows)
    wells_all = sum(r["wells"] for r in rows)
    summary = (
        f"{fields_right} of {len(rows)} field verdicts right; {wells_right} of {wells_all} "
        f"single-well verdicts right"
    )
    among = sum(r.get("right_among", r["right"]) for r in rows)
    if among != fields_right:
        summary += (
            f"; counting what a verdict cannot tell apart from its effect or names as the "
            f"next step: {among} of {len(rows)} fields, "
            f"{sum(r.get('wells_right_among', r['wells_right']) for r in rows)} of {wells_all} "
            "wells"
        )
    clean = [r for r in rows if r["case"] == "none"]
    if clean:
        summary += (
            f"; fields without a hidden effect: {sum(r['wells_right'] for r in clean)} of "
            f"{sum(r['wells'] for r in clean)} wells right, "
            f"{sum(r['wells_noise'] for r in clean)} of them 'noise'"
        )
    return summary


def _write_markdown(
    args: argparse.Namespace, rows: list[dict[str, Any]], planned: int, *, final: bool
) -> None:
    """The table so far (rewritten after every diagnosis, so that a run stopped early
    leaves what it measured, marked partial)."""
    seeds = args.seeds.split(",")
    lines = [
        f"## {', '.join(x.capitalize() for x in args.physics.split(','))} truth, "
        f"seed{'s' if len(seeds) > 1 else ''} {', '.join(seeds)}",
        "",
        "Written by `python benchmarks/bench_verdicts.py "
        f"--cases {args.cases} --combos {args.combos} --seeds {args.seeds} "
        f"--physics {args.physics} --wells {args.wells} --years {args.years} "
        f"--split {args.split}{f' --until {args.until}' if args.until else ''} --markdown ...` "
        "(seeds no test uses). Right: "
        + "; ".join(
            f"{physics}: "
            + ", ".join(f"{k} -> {expected(k, physics)}" for k in args.cases.split(","))
            for physics in args.physics.split(",")
        )
        + " (`effect` or `carried` naming it).",
        "",
        "| physics | case | seed | model | method | field verdict | right | among the named "
        "| wells right | live MAPE % | change of live MAPE (points) "
        "| trial forecast (points) | set aside as trend proxies | time s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        change = "" if not np.isfinite(r["change"]) else f"{r['change']:+.2f}"
        trial = "" if not np.isfinite(r.get("trial", np.nan)) else f"{r['trial']:+.2f}"
        lines.append(
            f"| {r['physics']} | {r['case']} | {r['seed']} | {r['model']} | {r['method']} "
            f"| {r['verdict']} | {'yes' if r['right'] else 'no'} "
            f"| {'yes' if r.get('right_among', r['right']) else 'no'} "
            f"| {r['wells_right']}/{r['wells']} | {r['live']:.2f} | {change} | {trial} "
            f"| {r.get('proxies', '')} | {r['time_s']:.0f} |"
        )
    lines.append("")
    if rows:
        lines.append(_summary(rows) + ".")
    if not final or len(rows) < planned:
        lines.append(
            f"\nPartial: {len(rows)} of the {planned} planned diagnoses are in the table "
            "(the run was stopped or is still running)."
        )
    lines.append("")
    Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
    temp = Path(args.markdown).with_suffix(".tmp")
    temp.write_text("\n".join(lines), encoding="utf-8")
    temp.replace(args.markdown)


if __name__ == "__main__":
    main()
