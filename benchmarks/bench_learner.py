"""One well's streaming learner: cost of a prediction and of an update, with a short and a
long remembered history, for online learning (``ol``, its default 10 steps) and the Bayesian
filter (``bayes``), side by side in one run (read the ratios: the machine is shared).

The learner remembers every measurement (for periodic retrains and model changes); an
update must not get slower as that history grows, and a Bayesian update must cost less
than an ``ol`` one. Run:

    python benchmarks/bench_learner.py [--rows 300000] [--updates 300]
"""

from __future__ import annotations

import argparse
import time

import pandas as pd
import torch

from vfm_core.learning import TrainSettings
from vfm_core.learning.streaming import WellLearner
from vfm_core.runtime import configure

SAMPLE = [
    0.5,
    60.0,
    20.0,
    70.0,
    0.1,
    0.6,
]  # choke -, p_up bar, p_down bar, t_up degC, eta_gas, eta_oil


def _learner(rows: int, effects: list[str], method: str) -> WellLearner:
    learner = WellLearner(
        "W01",
        "mm",
        method,
        effects=effects,
        train=TrainSettings(lr=0.03, max_iter=5, default_iter=5),
    )
    x = torch.tensor([SAMPLE], dtype=torch.float64).repeat(rows, 1)
    x[:, 0] += torch.linspace(-0.1, 0.1, rows, dtype=torch.float64)  # the choke moves
    y = torch.full((rows,), 1000.0, dtype=torch.float64)  # Sm3/h
    t = torch.arange(rows, dtype=torch.int64) * 60_000_000_000 + 1_500_000_000_000_000_000
    learner.fit_history(x, y, t)
    return learner


def _time(learner: WellLearner, updates: int) -> tuple[float, float]:
    start = pd.Timestamp(int(learner.memory.t.max()) + 10**12, tz="UTC")
    t0 = time.perf_counter()
    for i in range(updates * 10):
        learner.predict(SAMPLE, when=start + pd.Timedelta(seconds=i))
    predict = (time.perf_counter() - t0) / (updates * 10)
    t0 = time.perf_counter()
    for i in range(updates):
        learner.learn(SAMPLE, 1000.0, start + pd.Timedelta(hours=1, minutes=i), "mpfm")
    learn = (time.perf_counter() - t0) / updates
    return predict * 1e6, learn * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=300_000, help="long history, rows")
    parser.add_argument("--updates", type=int, default=300)
    args = parser.parse_args()
    configure(1)  # torch's threads, glibc's malloc: as the vfm command (vfm_core.runtime)
    print(f"{'model':<12} {'method':<6} {'history rows':>12} {'predict us':>11} {'update us':>10}")
    for effects in ([], ["erosion"]):
        name = "+".join(["mm", *effects])
        updates = {}
        for method in ("ol", "bayes"):
            figures = {}
            for rows in (1_000, args.rows):
                figures[rows] = _time(_learner(rows, effects, method), args.updates)
                print(
                    f"{name:<12} {method:<6} {rows:>12,} {figures[rows][0]:>11.0f} {figures[rows][1]:>10.0f}"
                )
            short, long = figures[1_000], figures[args.rows]
            print(
                f"{'':<12} {'':<6} {'long/short':>12} {long[0] / short[0]:>11.2f} {long[1] / short[1]:>10.2f}"
            )
            updates[method] = short[1]
        print(f"{name:<12} update bayes/ol: {updates['bayes'] / updates['ol']:.2f}")


if __name__ == "__main__":
    main()
