"""``vfm demo``: the whole product on an embedded default, nothing to install first.

1. Simulate a field: 5 wells over 3 years from 2016-01-01 (seed 0) with hidden choke
   erosion, so a model that stops learning goes stale (about 7,000 rows).
2. Start ``vfm serve`` in a subprocess (never a fork after Zenoh opened) with a fresh
   SQLite store, Zenoh and HTTP on free loopback ports, the hybrid ``ham`` model with
   online learning (``ol``), fitted on the first year.
3. Replay the remaining two years through it over Zenoh as fast as it takes them.
4. Run the offline study of the same file (``vfm evaluate``: last, mm and the service's
   model; ol and pbl:182d) and write its report (skip with --no-report).
5. Print the MAPE per well and overall, the ``last`` benchmark's for reference, and
   where to look next. The service stops at the end (or on Ctrl-C with --keep-serving).

SIGTERM and SIGINT (Ctrl-C) at any step stop the ``vfm serve`` child cleanly before the
demo exits (status 143 or 130): a stopped demo never leaves a service on its port.
"""

from __future__ import annotations

import argparse
import json
import secrets
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the demo imports its heavy parts when it runs, not when the CLI starts
    import pandas as pd

    from replay.replayer import ReplayResult

__all__ = ["register", "run_demo"]


def _config_text(
    out: Path,
    data: Path,
    split: str,
    model: str,
    method: str,
    token: str,
    effects: list[str] | None = None,
) -> str:
    return f"""# Written by `vfm demo`: the service's settings (see README.md, 'The streaming service').
prefix = "vfm"

[model]
name = "{model}"
method = "{method}"
effects = {json.dumps(effects or [])}
history = "{data.resolve()}"
history_until = "{split}"

[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:0"]   # a free loopback port

[http]
host = "127.0.0.1"
port = 0                        # a free port
token = "{token}"

[store]
path = "{(out / "store.sqlite").resolve()}"
synchronous = "normal"          # survives a killed process; "full" also survives power loss
"""


class _Stop(Exception):
    """SIGTERM or SIGINT: unwind, stopping the service child on the way out."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


#: the signal received during this run of the demo (empty: none), see :func:`run_demo`
_received: list[int] = []


def _stop_if_signalled() -> None:
    """Raise :class:`_Stop` again for a signal whose exception was swallowed: raised while
    the main thread was inside native code that called back into Python (a Zenoh put, for
    one), it is printed as "Exception ignored" and the run would go on. Called between the
    demo's steps."""
    if _received:
        raise _Stop(_received[0])


def run_demo(args: argparse.Namespace) -> int:
    """The demo, stopping its service child on SIGTERM and SIGINT (see the module docstring)."""
    if threading.current_thread() is not threading.main_thread():
        return _run_demo(args)
    _received.clear()

    def on_signal(signum: int, frame: Any) -> None:
        if _received:  # already unwinding: let the child's stop finish
            return
        _received.append(signum)
        raise _Stop(signum)

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        code = _run_demo(args)
        _stop_if_signalled()  # received at the very end, or swallowed on the way
        return code
    except _Stop as stop:
        print(f"vfm demo: {stop} received; the service was stopped.", file=sys.stderr, flush=True)
        return 128 + stop.signum
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _received.clear()


def _model_label(model: str, effects: list[str]) -> str | None:
    """The label of the demo's model (``mm+erosion`` with effects); None, with the sentence
    printed, when the effects do not apply to the model or a name is unknown."""
    if not effects:
        return model
    from vfm_core.effects import resolve_effects
    from vfm_core.errors import ConfigError

    if model not in ("mm", "hem", "ham"):
        print(
            f"vfm demo: --effects extend the physics models mm, hem and ham, not "
            f"'{model}'; choose --model mm, hem or ham.",
            file=sys.stderr,
        )
        return None
    try:
        return "+".join([model, *(c.name for c in resolve_effects(effects))])
    except ConfigError as exc:
        print(f"vfm demo: --effects: {exc}", file=sys.stderr)
        return None


def _run_demo(args: argparse.Namespace) -> int:
    import httpx

    from replay.replayer import replay_frame
    from vfm_core.fileio import write_text_atomic

    started = time.perf_counter()
    effects = [e.strip() for e in (args.effects or "").split(",") if e.strip()]
    # checked before anything runs: a bad name fails here, with its sentence
    label = _model_label(args.model, effects)
    if label is None:
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = out / "field.parquet"
    split = f"{2016 + args.history_years}-01-01"
    n_steps = 4 if args.no_report else 5
    frame = _simulate(args, data, n_steps)

    for stale in out.glob("store.sqlite*"):
        stale.unlink()
    token = secrets.token_urlsafe(24)
    config = out / "service.toml"
    write_text_atomic(
        config, _config_text(out, data, split, args.model, args.method, token, effects)
    )
    print(
        f"2/{n_steps} Starting `vfm serve` ({label} with {args.method}, fitted on the data before {split}) ...",
        flush=True,
    )
    from service.testing import (
        ServeProcess,  # the demo is the one replay module that starts a service
    )

    (out / "serve.log").unlink(missing_ok=True)
    proc = ServeProcess(config, out / "serve.log").start(timeout=300)
    http_url, zenoh_ep = proc.http_url, proc.zenoh
    try:
        print(f"    Service ready: HTTP {http_url}, Zenoh {zenoh_ep}.", flush=True)
        print(
            f"3/{n_steps} Replaying the rows from {split} on over Zenoh, as fast as the service takes them ...",
            flush=True,
        )
        result = replay_frame(
            frame, connect=[zenoh_ep], start=split, speed=None, progress=not args.quiet
        )
        _stop_if_signalled()
        health = httpx.get(f"{http_url}/health", timeout=10).json()
        wells = httpx.get(f"{http_url}/wells", timeout=10).json()

        offline = _offline(args, frame, split, effects, data, out, n_steps)
        print(f"{n_steps}/{n_steps} Results")
        _print_scores(result, offline, label, args.method, split)
        _print_service(health, wells)
        elapsed = time.perf_counter() - started
        print(f"\nDone in {elapsed:.0f} s. Where to look next:")
        _print_files(args, out, config, offline.report, split, effects)
        if args.keep_serving:
            _keep_serving(proc, http_url, zenoh_ep, token)
        else:
            print(
                "  API        run `vfm demo --keep-serving` to keep the service and its API running"
            )
    finally:
        proc.stop()
    return 0


def _simulate(args: argparse.Namespace, data: Path, n_steps: int) -> pd.DataFrame:
    """Step 1: the field with hidden choke erosion, written to ``data`` and read back."""
    from vfm_core.observations import load_observations
    from vfm_core.simulate import simulate_field, write_field

    print(
        f"1/{n_steps} Simulating {args.wells} wells over {args.years:g} years from 2016-01-01 (seed {args.seed}, "
        "hidden choke erosion) ...",
        flush=True,
    )
    field = simulate_field(wells=args.wells, years=args.years, seed=args.seed, hidden=["erosion"])
    write_field(field, data)
    print("    " + field.summary())
    return load_observations(data).frame


def _print_files(
    args: argparse.Namespace,
    out: Path,
    config: Path,
    report: Path | None,
    split: str,
    effects: list[str],
) -> None:
    """Where the demo's files are: the data, the store, the settings, the report (or the
    command that writes it)."""
    data = out / "field.parquet"
    print(f"  data       {data}  (the truth beside it: field.truth.json)")
    print(
        f"  store      {(out / 'store.sqlite').resolve()}  (SQLite: samples with predictions, "
        "measurements, checkpoints)"
    )
    print(f"  settings   {config}  (service log: {out / 'serve.log'})")
    if report is not None:
        print(f"  report     {report.resolve()}  (open in a browser)")
    else:
        # the models and methods the study of step 4 runs, each once (`--model mm`)
        models = ",".join(dict.fromkeys(["last", "mm", args.model]))
        methods = ",".join(dict.fromkeys([args.method, "pbl:182d"]))
        print(
            f"  report     .venv/bin/vfm evaluate {data} --out {out / 'study'} --models {models} "
            f"--methods {methods} --split {split}"
            + (f" --effects {','.join(effects)}" if effects else "")
        )


@dataclass
class _Offline:
    """What the demo ran offline: the benchmark's (``last``) predictions, the pooled MAPE
    (%) of each model and method of the study (empty with ``--no-report``) and its report."""

    last: pd.DataFrame
    mape: dict[tuple[str, str], float] = field(default_factory=dict)
    report: Path | None = None


def _offline(
    args: argparse.Namespace,
    frame: pd.DataFrame,
    split: str,
    effects: list[str],
    data: Path,
    out: Path,
    n_steps: int,
) -> _Offline:
    """The benchmark alone (``--no-report``), or the offline study of the same file with
    its report in ``out/study`` (step 4)."""
    from vfm_core.jobs.evaluate import run_study, write_study
    from vfm_core.jobs.study import mape, run_prequential

    if args.no_report:
        return _Offline(run_prequential(frame, "last", "ol", split=split).predictions)
    models = list(dict.fromkeys(["last", "mm", args.model]))
    print(
        f"4/{n_steps} The offline study of the same file (vfm evaluate: {', '.join(models)}"
        f"{', and with ' + '+'.join(effects) if effects else ''}; "
        f"{args.method} and pbl:182d) for the report ...",
        flush=True,
    )
    methods = list(dict.fromkeys([args.method, "pbl:182d"]))
    study = run_study(
        frame,
        models=models,
        methods=methods,
        split=split,
        effects=effects,
        progress=not args.quiet,
        data_path=str(data),
    )
    _stop_if_signalled()
    written = write_study(study, out / "study")
    preds = study.predictions
    return _Offline(
        last=preds[(preds["model"] == "last") & (preds["method"] == preds["method"].iloc[0])],
        mape={
            (str(m), str(meth)): mape(g["predicted"], g["measured"])
            for (m, meth), g in preds.groupby(["model", "method"], sort=False)
        },
        report=next((p for p in written if p.name == "report.html"), None),
    )


def _print_scores(
    result: ReplayResult, offline: _Offline, label: str, method: str, split: str
) -> None:
    """The service's MAPE per well beside the benchmark's, and the offline study's."""
    from vfm_core.jobs.study import mape, metrics_records

    last = offline.last
    # the total's record of each well: phase records (``"target": "q_oil"`` ...) follow it
    last_by_well = {r["well"]: r["mape"] for r in metrics_records(last) if "target" not in r}
    last_all = mape(last["predicted"], last["measured"])
    print(result.summary().split("MAPE of the")[0].rstrip())
    column = f"{label}+{method} (service)"
    print(
        f"\n  MAPE %, {len(result.scored):,} measurements after {split} (each predicted before learning from it)"
    )
    print(f"  {'well':<8} {column:>22} {'last (benchmark)':>17} {'n':>7}")
    for r in result.per_well.itertuples():
        print(
            f"  {r.well:<8} {r.mape:>22.2f} {last_by_well.get(r.well, float('nan')):>17.2f} {r.n:>7,}"
        )
    n_all = int(result.per_well["n"].sum())
    print(f"  {'all':<8} {result.overall_mape:>22.2f} {last_all:>17.2f} {n_all:>7,}")
    if offline.mape:
        same = offline.mape.get((label, method))
        others = ", ".join(f"{m}+{meth} {v:.2f}" for (m, meth), v in offline.mape.items())
        print(f"\n  Offline (vfm evaluate, pooled MAPE %): {others}.")
        if same is not None:
            print(
                f"  The service through Zenoh gave {result.overall_mape:.2f} for {label}+{method}; "
                f"the offline prequential run {same:.2f}."
            )


def _print_service(health: dict[str, Any], wells: list[dict[str, Any]]) -> None:
    """What the service took in, refused and dropped, and each well's model version."""
    rejected = health.get("rejected_total", 0)
    print(
        f"\n  The service took {health['accepted'].get('sensors', 0):,} samples and "
        f"{health['accepted'].get('measurements', 0):,} measurements, rejected {rejected}, "
        f"dropped {health['overflow']}; model versions now "
        + ", ".join(f"{w['well']}: {w['version']}" for w in sorted(wells, key=lambda w: w["well"]))
        + "."
    )


def _keep_serving(proc: Any, http_url: str, zenoh_ep: str, token: str) -> None:
    """Say where the running service answers, then wait until it ends or Ctrl-C."""
    print(f"  workbench  {http_url}/  (the page: every well, charts, diagnose and apply)")
    print(f"  API        {http_url}/docs  (e.g. curl {http_url}/wells/W01)")
    print(f"             POST well tests with: -H 'Authorization: Bearer {token}'")
    print(
        f"             model with the wear the field hides: curl -X PUT {http_url}/wells/W01/model "
        f"-H 'Authorization: Bearer {token}' -H 'content-type: application/json' "
        """-d '{"model": "mm", "effects": ["erosion"]}'"""
    )
    print(f"  Zenoh      {zenoh_ep}  (vfm replay DATA --connect {zenoh_ep})")
    print("The service keeps running; press Ctrl-C to stop it.", flush=True)
    interrupted = False
    try:
        while proc.proc is not None and proc.proc.poll() is None and not _received:
            time.sleep(0.5)
    except (KeyboardInterrupt, _Stop):
        interrupted = True
    if interrupted or _received:
        # Ctrl-C is how this mode ends: the service stops and the demo exits with 0
        _received.clear()
        print("\nStopping the service ...", flush=True)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "demo",
        help="the main job on an embedded default: simulate, serve, replay over Zenoh, score",
        description="Simulate a small field with hidden erosion, start the streaming service on free "
        "loopback ports, fit it on the first year, replay the rest through it over Zenoh and print the "
        "errors (a few minutes on two cores).",
    )
    p.add_argument("--out", default="runs/demo", help="output folder (default runs/demo)")
    p.add_argument("--wells", type=int, default=5, help="wells (default 5)")
    p.add_argument("--years", type=float, default=3.0, help="years simulated (default 3)")
    p.add_argument(
        "--history-years",
        type=int,
        default=1,
        help="years of history before the replay (default 1)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--model", default="ham", help="model of the service (default ham)")
    p.add_argument("--method", default="ol", help="learning method (default ol)")
    p.add_argument(
        "--effects",
        default="",
        help="physical effects extending the service's model (mm, hem or ham), comma-separated, "
        "e.g. erosion, the wear the demo's field hides (vfm diagnose names them; default none)",
    )
    p.add_argument(
        "--keep-serving", action="store_true", help="leave the service running until Ctrl-C"
    )
    p.add_argument("--no-report", action="store_true", help="skip the offline study and its report")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=run_demo)
