"""What declared key expressions cost a Zenoh session that receives: messages/s and CPU.

Why this exists: with zenoh 1.10, each publisher a session keeps declared under the
prefix of the keys it receives makes every message that session *receives* cost a match
against them, in Zenoh's own receiving thread (1,000 publishers under another prefix
cost far less: 11.8 against 5.1 µs a message in one run; undeclared ones cost nothing). A
service with one declared prediction publisher per well, and a field client with one
declared publisher per well's sensors, each paid it (a perf profile of ``vfm serve`` under a burst:
``Resource::get_matches`` in the ``rx`` thread). So the service now publishes with
``Session.put`` and the field client undeclares a key's publisher once it has matched.

Two processes on loopback: a receiver (a FifoChannel subscriber on ``bench/**``, read by
a Python thread that only takes each payload) that first declares ``--declared``
publishers on the wells' prediction keys, as the service did (``bench/<well>/prediction``),
and a sender that puts ``--messages`` JSON samples of 1,000 wells with BLOCK congestion
control. The sizes run one after the other in one run. Prints the receiver's
messages/s and its process CPU per message (all its threads: Zenoh's and Python's);
asserts nothing. Run::

    .venv/bin/python benchmarks/bench_zenoh_keys.py [--messages 40000] [--declared 0,1000]
"""

from __future__ import annotations

import argparse
import json
import select
import subprocess
import sys
import time

import zenoh

SAMPLE = json.dumps(
    {
        "time": "2026-01-01T00:00:00+00:00",
        "choke": 0.5,
        "p_up": 80.0,
        "p_down": 30.0,
        "t_up": 60.0,
        "eta_gas": 0.2,
        "eta_oil": 0.5,
    }
).encode()


def _config(listen: str | None = None, connect: str | None = None) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("peer"))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("adminspace/enabled", "true")
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps([listen]))
    if connect:
        cfg.insert_json5("connect/endpoints", json.dumps([connect]))
    return cfg


def receiver(messages: int, declared: int) -> None:
    from service.transport import session_locators

    with zenoh.open(_config(listen="tcp/127.0.0.1:0")) as s:
        sub = s.declare_subscriber("bench/**", zenoh.handlers.FifoChannel(4096))
        pubs = [s.declare_publisher(f"bench/W{i:05d}/prediction") for i in range(declared)]
        print(session_locators(s)[0], flush=True)
        n, t0, c0 = 0, 0.0, 0.0
        for sample in sub:
            sample.payload.to_bytes()
            if n == 0:
                t0, c0 = time.perf_counter(), time.process_time()
            n += 1
            if n == messages:
                break
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        print(json.dumps({"rate": (n - 1) / wall, "cpu_us": cpu / (n - 1) * 1e6}), flush=True)
        s.put("ack/done", b"", congestion_control=zenoh.CongestionControl.BLOCK)
        for pub in pubs:
            pub.undeclare()
        sub.undeclare()


def sender(endpoint: str, messages: int) -> None:
    from replay.client import field_config

    with zenoh.open(field_config([endpoint])) as s:
        done = s.declare_subscriber("ack/done", zenoh.handlers.FifoChannel(4))
        keys = [zenoh.KeyExpr(f"bench/W{i:05d}/sensors") for i in range(1000)]
        probe = s.declare_publisher(keys[0])
        deadline = time.monotonic() + 30
        while not getattr(probe.matching_status, "matching", False):
            if time.monotonic() > deadline:
                raise SystemExit("The receiver never matched.")
            time.sleep(0.01)
        probe.undeclare()
        for i in range(messages):
            s.put(keys[i % 1000], SAMPLE, congestion_control=zenoh.CongestionControl.BLOCK)
        done.recv()  # the receiver took them all (closing first would drop those queued)


def run(messages: int, declared: int, timeout: float) -> dict[str, float]:
    """The receiver's figures; NaN when the sender did not finish within ``timeout`` s."""
    me = [sys.executable, __file__]
    rx = subprocess.Popen(
        [*me, "--role", "receiver", "--messages", str(messages), "--declared", str(declared)],
        stdout=subprocess.PIPE,
        text=True,
    )
    failed = {"rate": float("nan"), "cpu_us": float("nan")}
    try:
        assert rx.stdout is not None
        if not select.select([rx.stdout], [], [], 60.0)[0]:
            return failed  # the receiver never opened its session
        endpoint = rx.stdout.readline().strip()
        subprocess.run(
            [*me, "--role", "sender", "--endpoint", endpoint, "--messages", str(messages)],
            check=True,
            timeout=timeout,
        )
        if not select.select([rx.stdout], [], [], 60.0)[0]:
            return failed
        line = rx.stdout.readline()
    except (subprocess.TimeoutExpired, subprocess.CalledProcessError):
        return failed
    finally:
        if rx.poll() is None:
            rx.kill()
    return dict(json.loads(line)) if line.strip() else failed


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--messages", type=int, default=40_000)
    parser.add_argument("--declared", default="0,1000", help="comma-separated counts")
    parser.add_argument("--timeout", type=float, default=120.0, help="per size, s")
    parser.add_argument("--role", choices=["receiver", "sender"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.messages < 2:
        parser.error("--messages must be at least 2 (the first message starts the clock)")
    if args.role == "receiver":
        receiver(args.messages, int(args.declared))
        return
    if args.role == "sender":
        sender(args.endpoint, args.messages)
        return
    print(
        f"A Zenoh receiver taking {args.messages:,} single-sample messages of 1,000 wells "
        "(BLOCK puts from another process), with publishers declared on its wells' prediction keys:"
    )
    for declared in [int(d) for d in args.declared.split(",")]:
        r = run(args.messages, declared, args.timeout)
        print(
            f"  {declared:>6,} declared publishers: {r['rate']:>9,.0f} messages/s, "
            f"{r['cpu_us']:6.1f} µs of the receiver's CPU a message"
        )


if __name__ == "__main__":
    main()
