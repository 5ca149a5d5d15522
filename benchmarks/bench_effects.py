"""What adding an effect costs: one update and one prediction with and without each effect.

For ``mm`` and ``ham`` with ``ol`` and ``bayes``, the service's two paths, side by side in
one run:

- one well: ``WellLearner.learn`` (one measured rate) and ``WellLearner.predict`` (one
  sample), median microseconds per call;
- many wells: ``learn_many`` and ``predict_many`` (vfm_core.learning.streaming) over ``--wells``
  learners in one call, median microseconds per well;

for the plain model and for the model with each library effect (``--effects``), with the
ratio effect / plain of each figure (1.0: the effect costs nothing; the issue's target is
at most 1.5). A learner is fitted on its well's first ``HISTORY`` measured rows (100
iterations, no early stopping), then every call takes the next row, one second later.
Within a model and method the plain model and the effects take turns call by call, in a
new random order each round, so a change in this shared machine's load (or a cold cache
after a long call) falls on all of them alike.
``--markdown PATH`` writes the table (``docs/benchmarks/generated/effects.md``).

    python benchmarks/bench_effects.py --markdown docs/benchmarks/generated/effects.md
"""

from __future__ import annotations

import argparse
import copy
import gc
import os
import random
import statistics
import time
from dataclasses import replace
from typing import Any

import pandas as pd
import torch

from vfm_core.fileio import write_text_atomic
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.observations import validate_frame
from vfm_core.runtime import configure, tune_malloc
from vfm_core.schema import INPUT_COLUMNS, TARGET
from vfm_core.simulate import simulate_field

#: measured rows a learner is fitted on before the timed calls
HISTORY = 200
#: the library effects compared by default (those that multiply the rate first), then a
#: suggested correction (linear in t_up; the seasonal form) and the critical ratio
EFFECTS = (
    "erosion,erosion_time,valve_equal_percentage,valve,mpfm_bias,real_gas,slip,"
    "suggest:driver=t_up,suggest:driver=day_of_year,critical_ratio"
)


def _learner(frame: pd.DataFrame, model: str, method: str, effect: str | None) -> tuple[Any, ...]:
    """A fitted ``WellLearner`` of the frame's first well (with ``effect``, if any), the
    later rows' inputs, rates and sources, and ``when(k)``: k + 1 seconds after the history."""
    from vfm_core.learning.streaming import WellLearner

    well = wells_of(frame)[0]
    rows = frame[(frame["well"] == well) & frame[TARGET].notna()]
    hist = rows.iloc[:HISTORY]
    learner = WellLearner(
        "W",
        model,
        method,
        train=replace(DEFAULT_TRAIN[model], max_iter=100, early_stopping=False),
        effects=[effect] if effect else [],
    )
    tests = hist["source"].eq("well_test") if "source" in hist else None
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy(dtype=float)),
        torch.tensor(hist[TARGET].to_numpy(dtype=float)),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
        well_test=None if tests is None else torch.tensor(tests.to_numpy(dtype=bool)),
    )
    live = rows.iloc[HISTORY:]
    xs = live[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
    ys = live[TARGET].to_numpy(dtype=float).tolist()
    src = live["source"].astype(str).tolist() if "source" in live else ["mpfm"] * len(live)
    t0 = pd.Timestamp(hist["time"].max())

    def when(k: int) -> pd.Timestamp:
        return t0 + pd.Timedelta(seconds=k + 1)

    return learner, xs, ys, src, when


def _turns(n: int, k: int) -> list[int]:
    """The order of round ``k``: a shuffle of the ``n`` learners, a new one each round (so
    that no learner always runs straight after another's calls, e.g. after a torch path's
    long call that leaves the caches cold)."""
    return random.Random(k).sample(range(n), n)


def group_costs(
    frame: pd.DataFrame,
    model: str,
    method: str,
    effects: list[str | None],
    n_wells: int,
    calls: int,
    warmup: int,
) -> list[dict[str, float]]:
    """Median microseconds, per effect (None: the plain model): ``learn`` and ``predict``
    of one well, and per well of ``learn_many`` and ``predict_many`` over ``n_wells``
    learners. The effects' calls take turns (one call of each, then the next round, in a
    new random order each round), so the shared machine's load falls on all alike."""
    from vfm_core.learning.streaming import learn_many, predict_many

    made = [_learner(frame, model, method, e) for e in effects]
    many = [[copy.deepcopy(m[0]) for _ in range(n_wells)] for m in made]
    times: list[dict[str, list[float]]] = [{c: [] for c in COLUMNS} for _ in effects]
    clock = time.perf_counter
    gc.disable()
    try:
        for k in range(calls + warmup):
            for i in _turns(len(made), k):
                (learner, xs, ys, src, when), got = made[i], times[i]
                n = len(xs)
                t0 = clock()
                learner.predict(xs[k % n], when=when(2 * k))
                t1 = clock()
                learner.learn(xs[k % n], ys[k % n], when(2 * k + 1), src[k % n])
                t2 = clock()
                if k >= warmup:
                    got["predict"].append((t1 - t0) * 1e6)
                    got["learn"].append((t2 - t1) * 1e6)
        per_call = max(8, calls // 8)  # a call covers every well: fewer calls
        for k in range(per_call + 2):
            for i in _turns(len(made), k):
                (_, xs, ys, src, when), wells, got = made[i], many[i], times[i]
                n = len(xs)
                x, y, s = [xs[k % n]] * n_wells, [ys[k % n]] * n_wells, [src[k % n]] * n_wells
                t0 = clock()
                learn_many(wells, x, y, [when(2 * k)] * n_wells, s)
                t1 = clock()
                predict_many(wells, x, [when(2 * k + 1)] * n_wells)
                t2 = clock()
                if k >= 2:
                    got["learn_many"].append((t1 - t0) * 1e6 / n_wells)
                    got["predict_many"].append((t2 - t1) * 1e6 / n_wells)
    finally:
        gc.enable()
    return [{c: statistics.median(v) for c, v in got.items()} for got in times]


COLUMNS = ("learn", "predict", "learn_many", "predict_many")


def _us(value: float) -> str:
    return f"{value:,.1f}" if value < 100 else f"{value:,.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", default="mm,ham", help="models, e.g. mm,ham")
    parser.add_argument("--methods", default="ol,bayes", help="learning methods, e.g. ol,bayes")
    parser.add_argument("--effects", default=EFFECTS, help="effects compared with the plain model")
    parser.add_argument("--wells", type=int, default=100, help="learners per *_many call")
    parser.add_argument("--calls", type=int, default=150, help="timed one-well calls per figure")
    parser.add_argument("--warmup", type=int, default=15)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--markdown", metavar="PATH", help="also write the table here")
    args = parser.parse_args()
    configure(1)
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"malloc kept for reuse: {tune_malloc()}, VFM_KERNELS={os.environ.get('VFM_KERNELS', '1')}"
    )
    field = simulate_field(wells=4, years=2.0, seed=args.seed)
    frame = validate_frame(field.observations).frame
    effects = [e for e in args.effects.split(",") if e]
    rows: list[tuple[str, str, str, dict[str, float], dict[str, float]]] = []
    header = f"{'model method effect':<36}" + "".join(f"{c:>22}" for c in COLUMNS)
    print("\nmicroseconds per call (one well) or per well (*_many); (x) = / the plain model")
    print(header)
    for model in [m for m in args.models.split(",") if m]:
        for method in [m for m in args.methods.split(",") if m]:
            group: list[str | None] = [None, *effects]
            found = group_costs(frame, model, method, group, args.wells, args.calls, args.warmup)
            plain = found[0]
            for effect, got in zip(group, found, strict=True):
                rows.append((model, method, effect or "(none)", got, plain))
                cells = "".join(f"{got[c]:>13,.1f} ({got[c] / plain[c]:4.2f}x)" for c in COLUMNS)
                print(f"{model + ' ' + method + ' ' + (effect or '(none)'):<36}{cells}", flush=True)
    worst = max((r[3][c] / r[4][c], r[0], r[1], r[2], c) for r in rows for c in COLUMNS)
    print(f"\nlargest ratio: {worst[0]:.2f}x ({worst[1]} {worst[2]} {worst[3]}, {worst[4]})")
    if args.markdown:
        write_text_atomic(args.markdown, markdown(args, rows))
        print(f"wrote {args.markdown}")


def markdown(args: argparse.Namespace, rows: list[tuple[str, str, str, dict, dict]]) -> str:
    """The run's table as a Markdown fragment (the command and the machine first)."""
    import platform
    import sys
    from datetime import UTC, datetime

    argv = " ".join(sys.argv[1:])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    kernels = os.environ.get("VFM_KERNELS", "1")
    lines = [
        f"Written by `python benchmarks/bench_effects.py {argv}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC (VFM_KERNELS={kernels}): torch "
        f"{torch.__version__}, one thread, {os.cpu_count()} CPUs ({platform.machine()}), load "
        f"average {load:.1f} at the end. One well: median of {args.calls} calls after "
        f"{args.warmup} warm-up calls, µs per call; many wells: `learn_many` / `predict_many` "
        f"over {args.wells} learners in one call, µs per well. In brackets: the figure over the "
        "plain model's of the same row group (the target: at most 1.5x).",
        "",
        "| model | method | effect | `learn`, µs | `predict`, µs | `learn_many`, µs/well "
        "| `predict_many`, µs/well |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for model, method, effect, got, plain in rows:
        cells = " | ".join(f"{_us(got[c])} ({got[c] / plain[c]:.2f}x)" for c in COLUMNS)
        lines.append(f"| {model} | {method} | {effect} | {cells} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
