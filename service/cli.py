"""``vfm serve [--config FILE]``: the streaming service in the foreground; ``vfm export
--store PATH --out FILE [--well W]``: a store's history in the observation format."""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

__all__ = ["register", "register_export"]

READY_LINE = "vfm serve: ready"


def _cmd_serve(args: argparse.Namespace) -> int:
    from service.app import Service, serve
    from service.config import load_settings

    settings = load_settings(args.config)
    logging.getLogger("vfm").setLevel(settings.log_level.upper())
    if not logging.getLogger().handlers:  # pragma: no cover - vfm_core.cli configures logging
        logging.basicConfig(format="%(levelname)s %(name)s: %(message)s")

    def ready(service: Service) -> None:
        engine = service.engine
        assert engine is not None
        # One line that scripts (the demo, tests) wait for; keep its format stable.
        print(
            f"{READY_LINE}: http={service.http_url} zenoh={','.join(service.locators) or '-'} "
            f"prefix={settings.prefix} wells={len(engine.wells)} store={settings.store.path} "
            f"owns={service.own.describe()}",
            flush=True,
        )
        print(f"API docs at {service.http_url}/docs; stop with Ctrl-C.", flush=True)

    return serve(settings, on_ready=ready)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "serve",
        help="run the streaming service: Zenoh in, predictions out, HTTP API",
        description="Answer every sensor sample on <prefix>/<well>/sensors with a prediction on "
        "<prefix>/<well>/prediction, learn from <prefix>/<well>/measurements/<source>, and serve the "
        "HTTP API (docs at /docs). Settings: --config FILE (TOML or JSON) and VFM_* environment "
        "variables (VFM_HTTP__PORT=8001).",
    )
    p.add_argument("--config", default=None, help="settings file (.toml or .json)")
    p.set_defaults(handler=_cmd_serve)
    _register_instances(subparsers)


def _cmd_instances(args: argparse.Namespace) -> int:
    import json

    import zenoh

    from service.config import ZenohSettings
    from service.scaleout import list_instances
    from service.transport import zenoh_config
    from vfm_core.errors import ConfigError
    from vfm_core.messages import validate_prefix, well_id_problem

    prefix = validate_prefix(args.prefix)
    if args.well is not None and (problem := well_id_problem(args.well)) is not None:
        raise ConfigError(problem)
    try:
        zs = ZenohSettings(mode=args.mode, connect=args.connect, listen=[])
    except ValueError:
        raise ConfigError(
            f"--connect {' '.join(args.connect)} is not a Zenoh endpoint list; write it like "
            "tcp/127.0.0.1:7447."
        ) from None
    try:
        session = zenoh.open(zenoh_config(zs, admin=False))
    except zenoh.ZError as exc:
        raise ConfigError(
            f"Zenoh could not connect to {', '.join(args.connect)}: {str(exc).rstrip('.')}. "
            "Check that the router runs there (--connect tcp/HOST:7447)."
        ) from None
    try:
        claims = list_instances(session, prefix, timeout=args.timeout)
    finally:
        session.close()
    if args.well is not None:
        claims = [c for c in claims if c.owns(args.well)]
    if args.json:
        print(json.dumps([c.__dict__ for c in claims], indent=2))
        return 0 if claims or args.well is None else 1
    if not claims:
        what = f"owns the well {args.well}" if args.well else f"serves under '{prefix}'"
        print(f"No running instance {what} (asked {', '.join(args.connect)}).")
        return 0 if args.well is None else 1
    for c in claims:
        print(f"{','.join(c.wells) or '*':<20} http={c.http or '-'} zenoh={c.zid}")
    return 0


def _register_instances(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "instances",
        help="list the running `vfm serve` instances and the wells each owns",
        description="Ask the Zenoh network which `vfm serve` instances serve under the prefix "
        "(each answers <prefix>/@instances/<zid> with its well patterns, zenoh.wells, and its "
        "HTTP address). With --well, only the instance that owns that well; exit code 1 when none.",
    )
    p.add_argument(
        "--connect",
        nargs="+",
        default=["tcp/127.0.0.1:7447"],
        help="Zenoh endpoint(s) of the router or of a service (default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--mode", choices=("client", "peer"), default="client")
    p.add_argument("--prefix", default="vfm", help="key-expression prefix (default vfm)")
    p.add_argument("--well", default=None, help="only the instance that owns this well")
    p.add_argument("--timeout", type=float, default=2.0, help="wait for answers, s (default 2)")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(handler=_cmd_instances)


def _cmd_export(args: argparse.Namespace) -> int:
    from service.export import export_store

    rows, path = export_store(args.store, args.out, args.well)
    what = f"well {args.well}" if args.well else "every well"
    print(f"Wrote {rows:,} rows of {what} from the store {args.store} to {path}.")
    return 0


def register_export(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "export",
        help="write a service store's history as an observation file (.parquet or .csv)",
        description="Read a `vfm serve` store (read-only: a running service is not disturbed) and "
        "write its samples and learned measurements in the observation format, with the "
        "service's predictions as extra columns (predicted, predicted_std, predicted_p05, "
        "predicted_p95, version). The file feeds vfm evaluate and vfm diagnose.",
    )
    p.add_argument("--store", required=True, help="the service's SQLite store (store.path)")
    p.add_argument("--out", required=True, help="output file, .parquet or .csv")
    p.add_argument("--well", default=None, help="only this well")
    p.set_defaults(handler=_cmd_export)


if __name__ == "__main__":  # pragma: no cover
    from vfm_core.cli import main

    sys.exit(main(["serve", *sys.argv[1:]]))
