"""``vfm diagnose`` on default-size fields with a known hidden effect: verdict, error, floor, time.

For every case a field is made, diagnosed with the defaults of ``vfm diagnose`` (``mm``,
online run ``ol``, comparisons fitted once before 2019-01-01), and one line printed: the
verdict (kind and effect or driver), the baseline and "with" MAPE of the headline (the same
protocol), the noise floor the diagnosis estimated and the one of the simulator's truth (the
true rate through each meter, meter drift included), the share of the error above the
(truth) floor removed, and the run time. One case at a time; each takes one to a few minutes
on two cores.

Cases: the simulator's hidden effects (``vfm simulate --hidden X``, 10 wells, 2016-2021,
seed 0), and hand-made fields that are not this simulator's: a clean field (seed 3) whose
rates are multiplied by a factor the library has no effect for (a temperature-dependent
discharge coefficient, weak and strong; a dependence on the separator pressure; a yearly
wave), or by another form of a library effect (an equal-percentage valve of rangeability 50
instead of 30, wear growing with time^1.5, a van der Waals gas instead of Papay's Z). Each line also gives the live baseline (the method replayed, ``--method``, default ``ol``)
and the outage baseline, the verdict's live and outage changes, and the run time with the
replay (format 3) and, with ``--before``, without it (``replay_top=0``: the fit-once verdict
of format 2): the cost of the replay. Run:

    python benchmarks/bench_diagnose.py [--cases none,erosion,tempcd] [--model mm] [--method ol]
        [--wells 10] [--years 6] [--before] [--out runs/bench-diagnose]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from vfm_core import physics as ph
from vfm_core.data import target_mask
from vfm_core.features import standard_features
from vfm_core.jobs.diagnose import run_diagnosis, write_diagnosis
from vfm_core.jobs.study import mape
from vfm_core.simulate import SimulatedField, simulate_field

SPLIT = pd.Timestamp("2019-01-01", tz="UTC")
LIBRARY = ("none", "erosion", "valve", "real_gas", "slip", "mpfm_bias", "critical_ratio")


def _temperature(k: float) -> Callable[[pd.DataFrame, SimulatedField], np.ndarray]:
    def factor(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
        return 1.0 + k * (obs["t_up"].to_numpy() - 60.0) / 10.0  # per 10 K above 60 degC

    return factor


def _separator(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
    return 1.0 + 0.15 * (obs["p_down"].to_numpy() - 25.0) / 10.0  # per 10 bar above 25 bar


def _season(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
    day = pd.DatetimeIndex(obs["time"]).day_of_year.to_numpy() - 1
    return 1.0 + 0.04 * np.sin(2 * np.pi * day / 365.25)


def _valve_r50(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
    u = torch.tensor(obs["choke"].to_numpy())
    return (ph.area_fraction(u, "equal_percentage", rangeability=50.0) / u).numpy()


def _wear_time(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
    return 1.0 + 0.04 * standard_features(obs)["years_on"].to_numpy() ** 1.5


def _van_der_waals(obs: pd.DataFrame, field: SimulatedField) -> np.ndarray:
    """The true rate with Z = 1 + p (b - a/RT)/RT (methane's a, b) over the ideal-gas one."""
    out = np.ones(len(obs))
    r_gas = 8.314462618
    for well, par in field.truth["wells"].items():
        sel = (obs["well"] == well).to_numpy()
        o = obs[sel]
        p1 = torch.tensor(o["p_up"].to_numpy() * 1e5)
        p2 = torch.tensor(o["p_down"].to_numpy() * 1e5)
        t1 = torch.tensor(o["t_up"].to_numpy() + 273.15)
        eg = torch.tensor(o["eta_gas"].to_numpy())
        eo = torch.tensor(o["eta_oil"].to_numpy())
        z = 1 + p1 * (4.31e-5 - 0.2303 / (r_gas * t1)) / (r_gas * t1)
        kw = {k: par[k] for k in ("rho_oil", "rho_wat", "kappa", "m_gas", "p_cr")}
        ideal = ph.choke_mass_flow(
            torch.tensor(1.0), p1, p2, t1, eg, eo, z=torch.ones_like(z), **kw
        )
        real = ph.choke_mass_flow(torch.tensor(1.0), p1, p2, t1, eg, eo, z=z, **kw)
        out[sel] = (real / ideal).numpy()
    return out


HANDMADE: dict[str, Callable[[pd.DataFrame, SimulatedField], np.ndarray]] = {
    "tempcd": _temperature(0.068),
    "tempcd_strong": _temperature(0.25),
    "separator": _separator,
    "season": _season,
    "valve_r50": _valve_r50,
    "wear_time": _wear_time,
    "van_der_waals": _van_der_waals,
}


def _case(name: str, wells: int = 10, years: float = 6.0) -> tuple[pd.DataFrame, float]:
    """The observations of a case and the truth's noise floor (MAPE %) after the split."""
    if name in LIBRARY:
        field = simulate_field(
            hidden=[] if name == "none" else [name], seed=0, wells=wells, years=years
        )
        factor = np.ones(len(field.observations))
    else:
        field = simulate_field(seed=3, wells=wells, years=years)
        factor = HANDMADE[name](field.observations, field)
    obs = field.observations.copy()
    obs["q_total"] = obs["q_total"] * factor
    truth = field.truth_samples["q_true"] * factor
    meter = field.truth_samples["mpfm_factor"].where(obs["source"] == "mpfm", 1.0)
    scored = target_mask(obs, "all") & (obs["time"] >= SPLIT).to_numpy()
    return obs, mape((truth * meter)[scored], obs["q_total"][scored])


def _num(value: object) -> float:
    return float(value) if isinstance(value, int | float) else float("nan")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", default=",".join([*LIBRARY, *HANDMADE]))
    parser.add_argument("--out", default="runs/bench-diagnose")
    parser.add_argument("--model", default="mm")
    parser.add_argument("--method", default="ol")
    parser.add_argument("--wells", type=int, default=10)
    parser.add_argument("--years", type=float, default=6.0)
    parser.add_argument(
        "--before", action="store_true", help="also time the fit-once verdict alone (format 2)"
    )
    args = parser.parse_args()
    print(
        f"{'case':<16} {'verdict':<34} {'baseline %':>10} {'with %':>7} {'floor est':>9} "
        f"{'floor truth':>11} {'removed':>8} {'time s':>7} {'outage %':>8} {'d live':>7} "
        f"{'d outage':>8} {'fit-once s':>10}"
    )
    for name in [c.strip() for c in args.cases.split(",") if c.strip()]:
        obs, truth_floor = _case(name, args.wells, args.years)
        before = float("nan")
        if args.before:
            started = time.perf_counter()
            run_diagnosis(obs, args.model, method=args.method, replay_top=0)
            before = time.perf_counter() - started
        started = time.perf_counter()
        diag = run_diagnosis(obs, args.model, method=args.method)
        elapsed = time.perf_counter() - started
        write_diagnosis(diag, Path(args.out) / name)
        h = diag.headline
        what = diag.verdict_effect or diag.verdict_driver or ""
        removed = (
            (h["baseline_mape"] - h["with_mape"]) / (h["baseline_mape"] - truth_floor)
            if h["with_mape"] is not None and h["baseline_mape"] > truth_floor
            else float("nan")
        )
        print(
            f"{name:<16} {diag.verdict_kind + ' ' + what:<34} {h['baseline_mape']:>10.2f} "
            f"{(h['with_mape'] or float('nan')):>7.2f} {(h['floor_mape'] or float('nan')):>9.2f} "
            f"{truth_floor:>11.2f} {100 * removed:>7.0f}% {elapsed:>7.0f} "
            f"{_num(h.get('outage_baseline_mape')):>8.2f} "
            f"{_num((h.get('live_change') or {}).get('change')):>+7.2f} "
            f"{_num((h.get('outage_change') or {}).get('change')):>+8.2f} {before:>10.0f}",
            flush=True,
        )
        (Path(args.out) / name / "headline.json").write_text(
            json.dumps({**h, "truth_floor": truth_floor, "runtime_s": elapsed}, default=str)
        )


if __name__ == "__main__":
    main()
