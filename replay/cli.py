"""``vfm replay DATA``: stream an observation file through a running service and score its answers."""

from __future__ import annotations

import argparse
from typing import Any

__all__ = ["register"]


def _cmd_replay(args: argparse.Namespace) -> int:
    from replay.replayer import replay_frame
    from vfm_core.observations import load_observations

    # a row whose only problem is an input outside its physical span is sent as it is: the
    # service raises an out_of_range fault on it (or refuses it, without fault detection)
    loaded = load_observations(args.data, keep_out_of_range=True)
    print(loaded.summary())
    result = replay_frame(
        loaded.frame,
        connect=args.connect or ["tcp/127.0.0.1:7447"],
        prefix=args.prefix,
        start=args.start,
        speed=None if args.max or args.speed is None else args.speed,
        mode=args.mode,
        match_timeout=args.match_timeout,
        idle_timeout=args.idle_timeout,
        progress=not args.quiet,
        readings=loaded.separators.readings if loaded.separators else None,
    )
    print(result.summary())
    if args.out:
        from pathlib import Path

        from vfm_core.fileio import write_with

        out = Path(args.out)
        scored = result.scored
        if out.suffix == ".csv":
            write_with(out, lambda path: scored.to_csv(path, index=False))
        else:
            write_with(out, lambda path: scored.to_parquet(path, index=False))
        print(f"Wrote the scored predictions to {out}.")
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "replay",
        help="stream an observation file over Zenoh through a running service, then score its predictions",
        description="Publish each row in time order (sensor sample, then its measurement; a "
        "separator's total on <prefix>/<separator>/measurements/separator) with BLOCK "
        "congestion control once the service's subscriber matched; collect the predictions and print "
        "their MAPE against the file's measurements per well and overall. A row with an input outside "
        "its physical span is sent with its raw values (an out_of_range fault in the service); a row "
        "with another problem is removed and counted.",
    )
    p.add_argument("data", help="observation file (.parquet or .csv)")
    pace = p.add_mutually_exclusive_group()
    pace.add_argument("--speed", type=float, default=None, help="N times real time")
    pace.add_argument(
        "--max", action="store_true", help="as fast as the service takes it (the default)"
    )
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint of the service or router (default tcp/127.0.0.1:7447); repeatable",
    )
    p.add_argument(
        "--mode",
        choices=["peer", "client"],
        default="peer",
        help="Zenoh mode (client when connecting to a router; default peer)",
    )
    p.add_argument("--prefix", default="vfm", help="key-expression prefix (default vfm)")
    p.add_argument("--start", default=None, help="replay rows from this date on (default: all)")
    p.add_argument(
        "--match-timeout",
        type=float,
        default=30.0,
        help="seconds to wait for the service's subscriber (default 30)",
    )
    p.add_argument(
        "--idle-timeout",
        type=float,
        default=3.0,
        help="at the end, stop waiting once no prediction came for this long (default 3 s)",
    )
    p.add_argument(
        "--out", default=None, help="also write the scored predictions (.parquet or .csv)"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(handler=_cmd_replay)
