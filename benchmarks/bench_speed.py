"""The cost of one online update and one prediction, side by side in one run (issue 16).

Prints the median cost per call (microseconds) of:

(a) a naive per-sample PyTorch loop: a linear model, one prediction and 10 Adam steps on
    the sample (the optimiser made once);
(b) river's ``StandardScaler | LinearRegression``, ``predict_one`` + ``learn_one`` (an
    optional benchmark dependency, ``pip install -e '.[bench]'``; skipped with the reason
    when it is not installed);
(c) one ``ol`` update (the method's defaults per model, ``DEFAULT_ONLINE``) and one
    prediction of ``mm``, ``hem`` and ``ham``, one well;
(d) one ``bayes`` update and one prediction of ``mm`` and ``ham``, one well;
(e) the same update of N wells in one batched call (the study's rounds, a service's batch),
    as the cost per well-update;
(f) the service's prediction path: ``WellLearner.predict`` of one well (features, retrains
    due, the model), and ``predict_many`` of N wells' learners in one call, per well;
(g) the service's learning path: ``WellLearner.learn`` of one well (retrains due, features,
    memory, the method's update), and ``learn_many`` of N wells' learners in one call, per
    well (``ol`` stacks the wells' updates; ``bayes`` learns one by one inside it);

and each one's ratio to (a). The plain ``mm``'s ``ol`` steps, ``bayes`` updates and
predictions run compiled (numba, ``vfm_core/learning/kernels.py``); its rows are repeated
with ``VFM_KERNELS=0``, the torch path, in the same run. Read the ratios: the machine may be shared. Each figure is
the median over ``--calls`` calls on a simulated well's stream after a short fit (every
call learns from the next measurement, as in the study), after ``--warmup`` calls.

    python benchmarks/bench_speed.py [--wells 10,100] [--calls 300] [--models mm,hem,ham]
        [--streaming-wells 100,1000] [--learning-wells 10,100] [--markdown PATH]

``--markdown PATH`` also writes the tables as a Markdown fragment (the command, the date,
the machine's load and the figures of this run), which the documentation site includes
(``docs/benchmarks/speed.md``): its figures are the script's, never copied by hand.

One torch thread (as the ``vfm`` command and the service run).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import os
import re
import statistics
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from vfm_core.data import Batch, make_batch, target_mask
from vfm_core.fileio import write_text_atomic
from vfm_core.jobs.study import wells_of
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, parse_method
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.runtime import configure, tune_malloc
from vfm_core.schema import INPUT_COLUMNS, TARGET
from vfm_core.simulate import simulate_field

#: samples per well the model is fitted on before the timed stream
HISTORY = 200


@contextlib.contextmanager
def _kernels(on: bool) -> Any:
    """The compiled ``mm`` online step on or off (``VFM_KERNELS``) inside the block."""
    before = os.environ.get("VFM_KERNELS")
    os.environ["VFM_KERNELS"] = "1" if on else "0"
    try:
        yield
    finally:
        if before is None:
            del os.environ["VFM_KERNELS"]
        else:
            os.environ["VFM_KERNELS"] = before


def _median_us(calls: list[Callable[[], object]], warmup: int) -> float:
    """Median wall time of each call, microseconds (the first ``warmup`` not counted)."""
    times = []
    gc.disable()
    try:
        for i, call in enumerate(calls):
            t0 = time.perf_counter()
            call()
            dt = time.perf_counter() - t0
            if i >= warmup:
                times.append(dt)
    finally:
        gc.enable()
    return statistics.median(times) * 1e6


def naive_torch(xs: np.ndarray, ys: np.ndarray, warmup: int) -> float:
    """(a) a linear model in float32, predict then 10 Adam steps on each sample."""
    x = torch.tensor((xs - xs.mean(0)) / (xs.std(0) + 1e-9), dtype=torch.float32)
    y = torch.tensor(ys / np.median(ys), dtype=torch.float32)
    model = torch.nn.Linear(x.shape[1], 1)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)

    def step(i: int) -> None:
        with torch.no_grad():
            model(x[i : i + 1])
        for _ in range(10):
            opt.zero_grad()
            loss = ((model(x[i : i + 1]).squeeze(-1) - y[i : i + 1]) ** 2).mean()
            loss.backward()
            opt.step()

    return _median_us([lambda i=i: step(i) for i in range(len(x))], warmup)


def river_cost(xs: np.ndarray, ys: np.ndarray, warmup: int) -> float | str:
    """(b) river's scaled linear regression, predict_one + learn_one; the reason if absent."""
    try:
        from river import linear_model, preprocessing
    except ImportError:
        return "river is not installed (pip install -e '.[bench]')"
    model = preprocessing.StandardScaler() | linear_model.LinearRegression()
    dicts = [dict(zip(INPUT_COLUMNS, map(float, row), strict=True)) for row in xs]

    def step(i: int) -> None:
        model.predict_one(dicts[i])
        model.learn_one(dicts[i], float(ys[i]))

    return _median_us([lambda i=i: step(i) for i in range(len(dicts))], warmup)


def tile_wells(batch: Batch, n_wells: int) -> Batch:
    """``batch``'s wells repeated (renamed) until there are ``n_wells`` (also used by
    ``bench_bayes_update.py``)."""
    reps = -(-n_wells // batch.n_wells)

    def rep(t: torch.Tensor) -> torch.Tensor:
        return t.repeat(reps, *([1] * (t.dim() - 1)))[:n_wells]

    assert batch.well_test is not None and batch.extra is not None
    names = [f"{w}_{k}" for k in range(reps) for w in batch.wells][:n_wells]
    return Batch(
        names,
        rep(batch.x),
        rep(batch.y),
        rep(batch.mask),
        rep(batch.time_ns),
        rep(batch.row),
        rep(batch.well_test),
        rep(batch.extra),
        batch.extra_names,
    )


def _stream(frame, n_wells: int, calls: int) -> tuple[Batch, list[Batch]]:
    """A history batch (``HISTORY`` samples per well) and ``calls`` one-sample columns after
    it, for ``n_wells`` wells (the simulated wells, repeated under new names)."""
    wells = wells_of(frame)
    rows = np.flatnonzero(target_mask(frame, "all"))
    batch = tile_wells(make_batch(frame, wells, rows), n_wells)
    rank = torch.cumsum(batch.mask.long(), 1)
    history = batch.select(rank <= HISTORY)
    cols = [batch.select(rank == HISTORY + 1 + k) for k in range(calls)]
    return history, cols


def learner_cost(
    model_name: str, method_text: str, history: Batch, cols: list[Batch], warmup: int
) -> tuple[float, float]:
    """Median cost of one update and of one prediction (every well of the batch), us."""
    model = make_model(model_name, history.wells)
    method = parse_method(method_text)
    train = replace(DEFAULT_TRAIN[model_name], max_iter=100, early_stopping=False)
    method.bind(model, train=train, online=DEFAULT_ONLINE[model_name])
    method.fit(history)
    method.start(int(history.time_ns[history.mask].max()))
    predict = _median_us([lambda c=c: method.predict(c) for c in cols], warmup)
    update = _median_us([lambda c=c: method.on_measurement(c) for c in cols], warmup)
    return update, predict


def _fitted_learner(frame, model_name: str, method_text: str) -> tuple[Any, list, list, Any]:
    """A ``WellLearner`` of the frame's first well fitted on its first ``HISTORY`` measured
    rows; the later rows' inputs and rates; and ``when(k)``: k + 1 seconds after the history."""
    import pandas as pd

    from vfm_core.learning.streaming import WellLearner

    wells = wells_of(frame)
    rows = frame[(frame["well"] == wells[0]) & frame[TARGET].notna()]
    hist = rows.iloc[:HISTORY]
    learner = WellLearner(
        "W",
        model_name,
        method_text,
        train=replace(DEFAULT_TRAIN[model_name], max_iter=100, early_stopping=False),
    )
    learner.fit_history(
        torch.tensor(hist[list(INPUT_COLUMNS)].to_numpy(dtype=float)),
        torch.tensor(hist[TARGET].to_numpy(dtype=float)),
        torch.tensor(pd.DatetimeIndex(hist["time"]).as_unit("ns").asi8),
    )
    live = rows.iloc[HISTORY:]
    xs = live[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
    ys = live[TARGET].to_numpy(dtype=float).tolist()
    t0 = pd.Timestamp(hist["time"].max())

    def when(k: int) -> pd.Timestamp:
        return t0 + pd.Timedelta(seconds=k + 1)

    return learner, xs, ys, when


def streaming_cost(
    frame, model_name: str, method_text: str, n_wells: int, calls: int, warmup: int
) -> tuple[float, float]:
    """Median cost of ``WellLearner.predict`` (one well) and of ``predict_many`` over
    ``n_wells`` learners, per well, us (every call one sample later)."""
    import copy

    from vfm_core.learning.streaming import predict_many

    learner, xs, _, when = _fitted_learner(frame, model_name, method_text)
    one = _median_us(
        [lambda k=k: learner.predict(xs[k % len(xs)], when=when(k)) for k in range(calls)],
        warmup,
    )
    many = [copy.deepcopy(learner) for _ in range(n_wells)]
    per_call = max(5, calls // 10)  # a call covers every well: fewer calls
    batched = _median_us(
        [
            lambda k=k: predict_many(many, [xs[k % len(xs)]] * n_wells, [when(calls + k)] * n_wells)
            for k in range(per_call + 2)
        ],
        2,
    )
    return one, batched / n_wells


def learning_cost(
    frame, model_name: str, method_text: str, n_wells: int, calls: int, warmup: int
) -> tuple[float, float]:
    """Median cost of ``WellLearner.learn`` (one well) and of ``learn_many`` over ``n_wells``
    learners, per well, us (every call learns the next measurement, one second later)."""
    import copy

    from vfm_core.learning.streaming import learn_many

    learner, xs, ys, when = _fitted_learner(frame, model_name, method_text)
    many = [copy.deepcopy(learner) for _ in range(n_wells)]  # before the one-well calls
    one = _median_us(
        [
            lambda k=k: learner.learn(xs[k % len(xs)], ys[k % len(ys)], when(k))
            for k in range(calls)
        ],
        warmup,
    )
    per_call = max(5, calls // 10)  # a call covers every well: fewer calls

    def call(k: int) -> None:
        x, y = xs[k % len(xs)], ys[k % len(ys)]
        learn_many(many, [x] * n_wells, [y] * n_wells, [when(k)] * n_wells)

    batched = _median_us([lambda k=k: call(k) for k in range(per_call + 2)], 2)
    return one, batched / n_wells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wells", default="10,100", help="batched well counts, e.g. 10,100")
    parser.add_argument("--calls", type=int, default=300, help="timed calls per figure")
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--models", default="mm,hem,ham", help="models run with ol")
    parser.add_argument("--bayes-models", default="mm,ham", help="models run with bayes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--streaming-wells", default="100,1000", help="(f): wells per predict_many call"
    )
    parser.add_argument("--learning-wells", default="10,100", help="(g): wells per learn_many call")
    parser.add_argument(
        "--markdown", metavar="PATH", help="also write the tables as a Markdown fragment here"
    )
    args = parser.parse_args()
    configure(1)  # torch's threads, glibc's malloc: as the vfm command (vfm_core.runtime)
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"malloc kept for reuse: {tune_malloc()} (VFM_MALLOC=default: glibc's defaults)"
    )
    field = simulate_field(wells=10, years=2.0, seed=args.seed)
    frame = validate_frame(field.observations).frame
    one = frame[(frame["well"] == wells_of(frame)[0]) & frame[TARGET].notna()]
    n_calls = args.calls + args.warmup
    xs = one[list(INPUT_COLUMNS)].to_numpy(dtype=float)[:n_calls]
    ys = one[TARGET].to_numpy(dtype=float)[:n_calls]

    rows: list[tuple[str, float, float | None]] = []  # (what, update us, predict us)
    naive = naive_torch(xs, ys, args.warmup)
    rows.append(("(a) naive torch loop: linear, predict + 10 Adam steps", naive, None))
    river = river_cost(xs, ys, args.warmup)
    if isinstance(river, str):
        print(f"(b) river: skipped, {river}")
    else:
        rows.append(("(b) river LinearRegression predict_one + learn_one", river, None))

    history, cols = _stream(frame, 1, n_calls)
    # (model, method, compiled kernel on): mm ol and bayes also with the torch path, side by side
    jobs = [(m, "ol", True) for m in args.models.split(",") if m]
    if "mm" in args.models.split(","):
        jobs.append(("mm", "ol", False))
    jobs += [(m, "bayes", True) for m in args.bayes_models.split(",") if m]
    if "mm" in args.bayes_models.split(","):
        jobs.append(("mm", "bayes", False))

    def name(model_name: str, method_text: str, kernel: bool) -> str:
        return f"{model_name} {method_text}{'' if kernel else ' (torch, VFM_KERNELS=0)'}"

    for model_name, method_text, kernel in jobs:
        with _kernels(kernel):
            update, predict = learner_cost(model_name, method_text, history, cols, args.warmup)
        steps = f", E={DEFAULT_ONLINE[model_name].steps}" if method_text == "ol" else ""
        label = "(c)" if method_text == "ol" else "(d)"
        what = f"{label} {name(model_name, method_text, kernel)}{steps}, 1 well"
        rows.append((what, update, predict))
    for n_wells in [int(w) for w in args.wells.split(",") if w]:
        history_n, cols_n = _stream(frame, n_wells, n_calls)
        for model_name, method_text, kernel in jobs:
            with _kernels(kernel):
                update, predict = learner_cost(
                    model_name, method_text, history_n, cols_n, args.warmup
                )
            rows.append(
                (
                    f"(e) {name(model_name, method_text, kernel)}, {n_wells} wells in one call, "
                    "per well",
                    update / n_wells,
                    predict / n_wells,
                )
            )

    streaming = []
    for model_name, method_text, kernel in jobs:
        for n_wells in [int(w) for w in args.streaming_wells.split(",") if w]:
            with _kernels(kernel):
                one_us, many_us = streaming_cost(
                    frame, model_name, method_text, n_wells, n_calls, args.warmup
                )
            streaming.append((name(model_name, method_text, kernel), n_wells, one_us, many_us))

    learning = []
    for model_name, method_text, kernel in jobs:
        for n_wells in [int(w) for w in args.learning_wells.split(",") if w]:
            with _kernels(kernel):
                one_us, many_us = learning_cost(
                    frame, model_name, method_text, n_wells, n_calls, args.warmup
                )
            learning.append((name(model_name, method_text, kernel), "", n_wells, one_us, many_us))

    print(f"\nmedian of {args.calls} calls, microseconds; ratio = (a) / this (higher is cheaper)")
    print(f"{'':<80} {'update us':>10} {'(a)/update':>10} {'predict us':>11}")
    for what, update, predict in rows:
        pred = "" if predict is None else f"{predict:11.1f}"
        print(f"{what:<80} {update:10.1f} {naive / update:10.2f} {pred:>11}")
    print("\n(f) the service's prediction path, microseconds per sample")
    print(f"{'':<58} {'predict, 1 well':>16} {'predict_many, per well':>24} {'ratio':>7}")
    for what, n_wells, one_us, many_us in streaming:
        label = f"{what}, {n_wells} wells per call"
        print(f"{label:<58} {one_us:16.1f} {many_us:24.1f} {one_us / many_us:7.1f}")
    print("\n(g) the service's learning path, microseconds per measurement")
    print(f"{'':<58} {'learn, 1 well':>16} {'learn_many, per well':>24} {'ratio':>7}")
    for what, _, n_wells, one_us, many_us in learning:
        label = f"{what}, {n_wells} wells per call"
        print(f"{label:<58} {one_us:16.1f} {many_us:24.1f} {one_us / many_us:7.1f}")
    if not isinstance(river, str):
        print(f"\nriver predict+learn: {river:.1f} us; prediction / that, per row above:")
        for what, _, predict in rows:
            if predict is not None:
                print(f"  {what:<60} {predict / river:8.1f} x")
    if args.markdown:
        text = markdown_tables(args, rows, naive, river, streaming, learning)
        write_text_atomic(args.markdown, text)
        print(f"\nwrote {args.markdown}")


def _md_us(value: float) -> str:
    """A cost in microseconds as the tables print it: a thousands comma, one decimal below 100."""
    return f"{value:,.1f}" if value < 100 else f"{value:,.0f}"


def markdown_tables(
    args: argparse.Namespace,
    rows: list[tuple[str, float, float | None]],
    naive: float,
    river: float | str,
    streaming: list[tuple[str, int, float, float]],
    learning: list[tuple[str, str, int, float, float]],
) -> str:
    """This run's tables as a Markdown fragment (microseconds; the command and machine first)."""
    import platform
    import sys
    from datetime import UTC, datetime

    argv = " ".join(sys.argv[1:])
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        f"Written by `python benchmarks/bench_speed.py {argv}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC: torch {torch.__version__}, one thread, "
        f"{os.cpu_count()} CPUs ({platform.machine()}), load average {load:.1f} at the end. "
        f"Median of {args.calls} calls after {args.warmup} warm-up calls, microseconds; "
        "(a) / update: how many times cheaper than the naive loop (higher is cheaper).",
        "",
        "| per call | update, µs | (a) / update | prediction, µs |",
        "| --- | ---: | ---: | ---: |",
    ]
    for what, update, predict in rows:
        pred = "" if predict is None else _md_us(predict)
        lines.append(f"| {what} | {_md_us(update)} | {naive / update:,.2f} | {pred} |")
    if isinstance(river, str):
        lines += ["", f"(b) river: skipped, {river}."]
    lines += [
        "",
        "(f) The service's prediction path, µs per sample:",
        "",
        "| learner | wells per call | `predict`, 1 well | `predict_many`, per well | ratio |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for what, n_wells, one_us, many_us in streaming:
        lines.append(
            f"| {what} | {n_wells:,} | {_md_us(one_us)} | {_md_us(many_us)} | "
            f"{one_us / many_us:.1f} |"
        )
    lines += [
        "",
        "(g) The service's learning path, µs per measurement:",
        "",
        "| learner | wells per call | `learn`, 1 well | `learn_many`, per well | ratio |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for what, _, n_wells, one_us, many_us in learning:
        lines.append(
            f"| {what} | {n_wells:,} | {_md_us(one_us)} | {_md_us(many_us)} | "
            f"{one_us / many_us:.1f} |"
        )
    if not isinstance(river, str):
        lines += [
            "",
            f"(b) river's predict + learn took {_md_us(river)} µs; each prediction above over it: "
            + ", ".join(
                f"{re.sub(r', E=[0-9]+', '', what.replace(', 1 well', ''))} {predict / river:.1f}x"
                for what, _, predict in rows
                if predict is not None and "wells in one call" not in what
            )
            + ".",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
