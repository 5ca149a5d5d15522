"""The ``vfm`` command line: one entry point, one subcommand per job.

Errors the VFM raises on purpose (:class:`vfm_core.errors.VFMError`) print one sentence
and exit with status 2; Ctrl-C exits with 130 and leaves no half-written output.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from vfm_core.errors import ConfigError, VFMError
from vfm_core.runtime import configure

__all__ = ["main", "build_parser"]

Handler = Callable[[argparse.Namespace], int]


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number.") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not a positive number of processes.")
    return value


def _split_list(values: Sequence[str] | None) -> list[str]:
    out: list[str] = []
    for v in values or []:
        out.extend(x.strip() for x in v.split(",") if x.strip())
    return out


# --- simulate -----------------------------------------------------------------------------
def _cmd_simulate(args: argparse.Namespace) -> int:
    from vfm_core.simulate import parse_hidden, simulate_field, write_field

    hidden = parse_hidden(args.hidden or ["none"])
    started = time.perf_counter()
    simulate: Any = simulate_field
    if args.separator is not None or args.separators is not None:
        from functools import partial

        from vfm_core.separator_sim import simulate_separator_field

        simulate = partial(
            simulate_separator_field,
            separators=args.separators or 1,
            name=args.separator or "SEP",
            noise=args.separator_noise,
        )
    sampling = _sampling(args.sample_every, separator=simulate is not simulate_field)
    field = simulate(
        wells=args.wells,
        years=args.years,
        seed=args.seed,
        hidden=hidden,
        start=args.start,
        progress=not args.quiet,
        physics=args.physics,
        valves=_split_list(args.valves),
        gas_lift=args.gas_lift,
        **sampling,
    )
    field = _with_faults(field, args.fault or [])
    paths = write_field(field, args.out)
    elapsed = time.perf_counter() - started
    print(field.summary())
    print(f"Wrote {', '.join(str(p) for p in paths)} in {elapsed:.1f} s.")
    return 0


def _sampling(every: float | None, separator: bool) -> dict[str, Any]:
    """``--sample-every DAYS`` as ``simulate_field``'s keyword (none without it)."""
    if every is None:
        return {}
    if not (math.isfinite(every) and 0.01 <= every <= 365):
        raise ConfigError(
            f"--sample-every {every:g}: give the days between a well's samples, 0.01 to 365 "
            "(e.g. 7 for weekly)."
        )
    if separator:
        raise ConfigError(
            "--sample-every does not go with --separator: a separator field samples every "
            "well daily at the same instant (its reading is the sum at that instant)."
        )
    return {"sample_every_days": every}


def _with_faults(field: Any, specs: Sequence[str]) -> Any:
    """``--fault WELL,SENSOR,KIND,START[,SIZE[,DAYS]]``: instrument faults put into the
    observations (:func:`vfm_core.faults_sim.inject_fault`), the truth's ``faults`` listing
    them; the true rates are left as they were."""
    if not specs:
        return field
    from dataclasses import replace

    from vfm_core.faults_sim import inject_fault

    frame, faults = field.observations, []
    for spec in specs:
        parts = [p.strip() for p in spec.split(",")]
        if not 4 <= len(parts) <= 6:
            raise ConfigError(
                f"--fault {spec[:80]!r}: write WELL,SENSOR,KIND,START[,SIZE[,DAYS]], e.g. "
                "W01,p_down,frozen,2017-03-01,,30."
            )
        well, sensor, kind, start, *rest = parts
        try:
            size = float(rest[0]) if rest and rest[0] else None
            days = float(rest[1]) if len(rest) > 1 and rest[1] else None
        except ValueError:
            raise ConfigError(f"--fault {spec[:80]!r}: SIZE and DAYS must be numbers.") from None
        frame, truth = inject_fault(frame, well, sensor, kind, start, size=size, days=days)
        faults.append(truth)
    field = replace(field, observations=frame)
    field.truth["faults"] = faults
    return field


# --- import-volve -------------------------------------------------------------------------
def _cmd_import_volve(args: argparse.Namespace) -> int:
    from vfm_core.volve import import_volve

    report = import_volve(args.src, args.out, min_choke_dp_bar=args.min_choke_dp)
    print(report.summary())
    return 0


# --- evaluate -----------------------------------------------------------------------------
def _cmd_evaluate(args: argparse.Namespace) -> int:
    from vfm_core.jobs.workers import StudyWorkers, usable_cpus
    from vfm_core.models import MODELS

    # the workers start first: they import the study and the kernels, seconds, while this
    # process imports its own and reads the data; then they serve every case
    models = _split_list(args.models) or list(MODELS)
    groups = len(models) * (2 if args.effects else 1)  # a group: one model's runs
    jobs = min(args.jobs or usable_cpus(), groups)
    preload = ("vfm_core.jobs.evaluate",)  # vfm_core.jobs.evaluate.PRELOAD
    with StudyWorkers(jobs - 1, threads=args.threads, preload=preload) as workers:
        return _evaluate_with(args, workers if jobs > 1 else None, jobs)


def _evaluate_with(args: argparse.Namespace, workers: Any, jobs: int) -> int:
    from vfm_core.jobs.evaluate import (
        DEFAULT_METHODS,
        format_summary,
        run_study,
        slow_runs,
        write_study,
    )
    from vfm_core.models import MODELS
    from vfm_core.observations import load_observations, outside_span
    from vfm_core.sensor_faults import write_sensor_faults

    # with the detectors on, a reading outside its physical span is kept (an out_of_range
    # fault: stood in for, not learned); taken as read, it is removed as before
    loaded = load_observations(args.data, keep_out_of_range=not args.no_sensor_faults)
    print(loaded.summary())
    models = _split_list(args.models) or list(MODELS)
    methods = _split_list(args.methods) or list(DEFAULT_METHODS)
    targets = _split_list(args.targets) or ["all"]
    params = None
    if args.params:
        from vfm_core.jobs.tune import load_params

        params = load_params(args.params)
    if jobs > 1:
        print(f"Running models in {jobs} processes (--jobs 1: all in this one).")
    studies: list[Any] = []
    if loaded.separators:  # the separators' totals: learned from and allocated (case 2)
        from vfm_core.jobs.evaluate import run_separator_study

        # the allocation takes every input as read: without the rows kept out of span
        frame = loaded.frame
        if loaded.kept:
            frame = frame[~outside_span(frame).any(axis=1)].reset_index(drop=True)
        studies, lines = run_separator_study(
            frame,
            loaded.separators,
            models=models,
            methods=methods,
            split=args.split,
            seed=args.seed,
            progress=not args.quiet,
        )
        print("\n".join(lines))
    for case in targets:
        result = run_study(
            loaded.frame,
            models=models,
            methods=methods,
            targets=case,
            split=args.split,
            seed=args.seed,
            progress=not args.quiet,
            data_path=str(args.data),
            track_parameters=args.track_parameters,
            params=params,
            effects=_split_list(args.effects),
            outages=_split_list(args.outages),
            outage_fractions=args.outage_fractions,
            workers=workers,
            sensor_faults=not args.no_sensor_faults,
        )
        out = Path(args.out) if len(targets) == 1 else Path(args.out) / case
        written = write_study(result, out, report=not args.no_report, separators=studies)
        written.append(write_sensor_faults(loaded.frame, out))  # vfm_core.sensor_faults
        print(format_summary(result))
        for sentence in slow_runs(result.runs):
            print(f"Slow run: {sentence}")
        print(f"Study took {result.runtime_s:.1f} s. Wrote {', '.join(str(p) for p in written)}.")
    return 0


def _add_separator_options(p: argparse.ArgumentParser) -> None:
    """``vfm simulate --separator [NAME] [--separators K] [--separator-noise REL]``."""
    p.add_argument(
        "--separator",
        nargs="?",
        const="SEP",
        metavar="NAME",
        help="all wells flow to one separator (name default SEP): daily synchronised "
        "samples, per-well rates hidden, well tests as usual, one total a day (Sm3/h)",
    )
    p.add_argument(
        "--separators",
        type=int,
        metavar="K",
        help="with --separator: K separators (NAME1..NAMEK), wells shared out in turn",
    )
    p.add_argument(
        "--separator-noise",
        type=float,
        default=0.015,
        metavar="REL",
        help="relative sd of the separator's total (default 0.015 = 1.5 %%)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vfm",
        description="Streaming virtual flow meter: choke models that keep learning from MPFM "
        "readings and well tests. Units: bar absolute, degC, Sm3/h.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log details")
    parser.add_argument(
        "--threads",
        type=int,
        default=int(os.environ.get("VFM_TORCH_THREADS", "1")),
        help="torch threads (default 1, or VFM_TORCH_THREADS): the tensors are small",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    _add_simulate(sub)

    _add_import_volve(sub)
    _add_evaluate(sub)

    for module in _INTERNAL_COMMANDS:
        import importlib

        importlib.import_module(module).register(sub)
    _register_plugins(sub)
    return parser


def _add_simulate(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("simulate", help="simulate a well field with a known truth")
    p.add_argument("--out", required=True, help="output observation file (.parquet or .csv)")
    p.add_argument("--wells", type=int, default=10, help="number of wells (default 10)")
    p.add_argument(
        "--years", type=float, default=5.0, help="length of history in years (default 5)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same file)")
    p.add_argument(
        "--start", default="2016-01-01", help="first day of the field (default 2016-01-01)"
    )
    p.add_argument(
        "--hidden",
        action="append",
        metavar="EFFECT",
        help="hidden effect(s), e.g. erosion, valve:family=sigmoid, real_gas, slip, "
        "mpfm_bias, critical_ratio, or none; repeat or comma-separate",
    )
    p.add_argument(
        "--physics",
        default="sachdeva",
        metavar="NAME",
        help="truth physics: sachdeva (default, the model mm carries), bernoulli (Bernoulli "
        "choke, Simpson's multiplier, fixed critical ratio, Hall-Yarborough real gas), or "
        "gilbert (Gilbert/Ros/Baxendell/Achong bean correlations)",
    )
    p.add_argument(
        "--valves",
        action="append",
        metavar="FAMILY",
        help="valve characteristics given to the wells in turn: linear, equal_percentage, "
        "quick_opening, convex, sigmoid, or mixed (all in turn); comma-separate",
    )
    p.add_argument(
        "--gas-lift",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of wells on gas lift, 0..1 (lift gas raises the gas fraction at the "
        "choke; default 0)",
    )
    p.add_argument(
        "--sample-every",
        type=float,
        default=None,
        metavar="DAYS",
        help="sample every well's sensors every DAYS days (e.g. 7: weekly, as some fields "
        "log); default the simulator's irregular few-hours-to-a-day sampling",
    )
    p.add_argument(
        "--fault",
        action="append",
        metavar="WELL,SENSOR,KIND,START[,SIZE[,DAYS]]",
        help="an instrument fault in the observations (kinds frozen, spike, drift, offset, "
        "out_of_range; sensors choke, p_up, p_down, t_up, eta_gas, eta_oil), e.g. "
        "W01,p_down,frozen,2017-03-01,,30; repeat for more",
    )
    _add_separator_options(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_simulate)


def _add_import_volve(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """``vfm import-volve SRC --out FILE``."""
    p = sub.add_parser("import-volve", help="convert Equinor's Volve daily production CSV")
    p.add_argument("src", help="volve_daily_production.csv")
    p.add_argument("--out", required=True, help="output observation file (.parquet or .csv)")
    p.add_argument(
        "--min-choke-dp",
        type=float,
        default=0.0,
        metavar="BAR",
        help="leave out days with less than this pressure drop across the choke, where it "
        "does not restrict the flow (default 0: keep every day)",
    )
    p.set_defaults(handler=_cmd_import_volve)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """``vfm evaluate DATA --out DIR``: the study and its options."""
    p = sub.add_parser("evaluate", help="run the study: models x learning methods, prequentially")
    p.add_argument("data", help="observation file (.parquet or .csv)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--models", action="append", help="comma-separated models (default: all)")
    p.add_argument(
        "--methods",
        action="append",
        help="comma-separated methods: ol, pbl:<period>[:window=<span>], pbl:auto, "
        "bayes[:option=value...] (default: ol,pbl:14d,pbl:182d)",
    )
    p.add_argument(
        "--targets",
        action="append",
        help="all (MPFM and well tests) or well_test; both: all,well_test (default all)",
    )
    p.add_argument(
        "--split",
        default=None,
        help="first day scored (default 2019-01-01 for all, 2020-01-01 for well_test, or, "
        "where that date does not fall inside the data, the first day of the month by which "
        "two thirds of the case's measurements were taken)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-report", action="store_true", help="skip report.html")
    p.add_argument(
        "--params",
        default=None,
        help="settings chosen by `vfm tune` (params.json); default: built-in defaults",
    )
    p.add_argument(
        "--effects",
        action="append",
        help="physical effects to add to mm/hem/ham (shown beside the plain model), "
        "e.g. erosion,real_gas or mypkg.effects:Scale",
    )
    p.add_argument(
        "--outages",
        action="append",
        help="also score the outage protocol: hide measurement windows of these lengths in "
        "the test period from learning and score inside them, e.g. 7d,30d,90d",
    )
    p.add_argument(
        "--outage-fractions",
        choices=("held", "measured"),
        default="held",
        help="phase fractions inside an outage window: held at the last measurement before "
        "it (default, as with a failed MPFM) or as measured in the file",
    )
    p.add_argument(
        "--track-parameters",
        action="store_true",
        help="also write parameters.parquet (physical parameters after each update)",
    )
    p.add_argument(
        "--jobs",
        type=_positive_int,
        default=None,
        help="processes that run models at once (default: the CPUs this process may use; "
        "1 runs everything in this process); the results are the same",
    )
    p.add_argument(
        "--no-sensor-faults",
        action="store_true",
        help="learn from every measurement and predict with the inputs as read, even at an "
        "instrument fault the detectors flag (default: hold and stand in, as the service does)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_evaluate)


#: vfm_core modules that bring their own subcommands (each has ``register(subparsers)``).
_INTERNAL_COMMANDS: tuple[str, ...] = (
    "vfm_core.jobs.tune",
    "vfm_core.jobs.drift_period",
    "vfm_core.jobs.diagnose",
)


def _register_plugins(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add subcommands registered under the ``vfm.commands`` entry-point group.

    Each entry point is a ``register(subparsers)`` function that adds its parser(s) and
    sets ``handler``. A plugin that fails to import is
    reported, not fatal, so the offline commands keep working.
    """
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group="vfm.commands"), key=lambda e: e.name):
        try:
            register = ep.load()
        except Exception as exc:  # a broken optional part must not take the CLI down
            logging.getLogger("vfm.cli").warning("Command '%s' is unavailable: %s", ep.name, exc)
            continue
        if ep.name in sub.choices:
            logging.getLogger("vfm.cli").warning(
                "Command '%s' from %s is ignored: a built-in command has that name.",
                ep.name,
                ep.value,
            )
            continue
        register(sub)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    handler: Handler = args.handler
    configure(args.threads)  # torch's threads and glibc's malloc (vfm_core.runtime)
    try:
        return handler(args)
    except VFMError as exc:
        print(f"vfm {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"vfm {args.command}: interrupted; no partial output was kept.", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
