"""Helpers to run the real service on loopback: for the tests, the demo and the benchmark.

Nothing here fakes a part: :func:`loopback_settings` makes settings with a Zenoh
listener on a free loopback port (multicast scouting off), HTTP on a free port and a
store in the given folder; :class:`ServeProcess` runs ``vfm serve`` in a subprocess
(spawned, never forked after Zenoh opened) and waits for its ready line. The field side
(sending inputs, collecting predictions) is :class:`replay.client.FieldClient`.
"""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from service.config import Settings, load_settings
from vfm_core.errors import VFMError

__all__ = ["loopback_settings", "ServeProcess", "wait_until", "READY"]

READY = re.compile(r"vfm serve: ready: http=(?P<http>\S+) zenoh=(?P<zenoh>\S+)")


def loopback_settings(folder: str | Path, **overrides: Any) -> Settings:
    """Settings for a loopback-only service with its store in ``folder`` (overrides as keyword trees)."""
    base: dict[str, Any] = {
        "zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:0"], "connect": []},
        "http": {"host": "127.0.0.1", "port": 0},
        "store": {"path": str(Path(folder) / "store.sqlite"), "synchronous": "normal"},
    }
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(base.get(key), dict):
            base[key] = {**base[key], **value}
        else:
            base[key] = value
    return load_settings(None, **base)


def study_settings(
    folder: str | Path,
    data: str | Path,
    name: str,
    method: str,
    until: str,
    train: dict[str, Any],
    *,
    review: bool = False,
    **overrides: Any,
) -> Settings:
    """:func:`loopback_settings` for a service that learns as the study does: model ``name``
    with ``method``, fitted on ``data``'s rows before ``until`` with ``train``, its retrains
    without a wall-clock cut (the study's retrains, exactly) and, unless ``review``, the
    well-test review off (a QC rule of the service that the study has not: it may hold a
    well test the study learns)."""
    model = {
        "name": name,
        "method": method,
        "history": str(data),
        "history_until": until,
        "train": train,
        "retrain_budget_s": 0,
    }
    if not review:
        overrides.setdefault("well_test_review", {"enabled": False})
    return loopback_settings(folder, model=model, **overrides)


def wait_until(predicate: Any, timeout: float, what: str, interval: float = 0.05) -> None:
    """Poll ``predicate`` until it is true; TimeoutError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def _pump(stream: IO[str], lines: queue.Queue[str], log: IO[str]) -> None:
    for line in stream:
        log.write(line)
        log.flush()
        lines.put(line)


#: the checkout (or installed location) this package is imported from
_TREE = str(Path(__file__).resolve().parents[1])


class ServeProcess:
    """``vfm serve --config FILE`` in a subprocess; ``http_url`` and ``zenoh`` once ready."""

    def __init__(
        self, config: str | Path, log_path: str | Path, *, env: dict[str, str] | None = None
    ) -> None:
        self.config = Path(config)
        self.log_path = Path(log_path)
        self.env = env
        self.proc: subprocess.Popen[str] | None = None
        self.http_url = ""
        self.zenoh = ""
        self._log: IO[str] | None = None
        self._pump: threading.Thread | None = None

    def start(self, timeout: float = 120.0) -> ServeProcess:
        cmd = [
            sys.executable,
            "-m",
            "vfm_core.cli",
            "serve",
            "--config",
            str(self.config.resolve()),
        ]
        log = self._log = self.log_path.open("a", encoding="utf-8")
        self.proc = subprocess.Popen(
            cmd,
            # ``-m`` imports from the working directory first: run from the tree this code
            # comes from, so the child serves the same code as its parent (a benchmark of
            # another checkout, say), whatever directory the parent runs in
            cwd=_TREE,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            bufsize=1,
            env={**os.environ, "PYTHONUNBUFFERED": "1", **(self.env or {})},
        )
        lines: queue.Queue[str] = queue.Queue()
        assert self.proc.stdout is not None
        self._pump = threading.Thread(
            target=_pump, args=(self.proc.stdout, lines, log), daemon=True
        )
        self._pump.start()
        deadline = time.monotonic() + timeout
        try:
            while time.monotonic() < deadline:
                try:
                    line = lines.get(timeout=0.2)
                except queue.Empty:
                    if self.proc.poll() is not None:
                        break
                    continue
                m = READY.search(line)
                if m:
                    self.http_url, self.zenoh = m["http"], m["zenoh"].split(",")[0]
                    return self
        except BaseException:  # interrupted while waiting: never leave the child behind
            self.stop()
            raise
        code = self.proc.poll()  # ended by itself (e.g. a bad setting), or still starting
        self.stop()
        tail = self.log_path.read_text(encoding="utf-8", errors="replace")[-2000:]
        what = (
            f"did not become ready within {timeout:.0f} s"
            if code is None
            else f"ended (exit code {code}) before it was ready"
        )
        raise VFMError(f"`vfm serve` {what}; log {self.log_path}:\n{tail}")

    def kill9(self) -> None:
        """SIGKILL: no cleanup at all, as in a crash."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._close_files()

    def _close_files(self) -> None:
        if self._pump is not None:
            self._pump.join(5)  # ends at EOF, once the process is gone
            self._pump = None
        if self.proc is not None and self.proc.stdout is not None:
            self.proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None

    def stop(self, timeout: float = 30.0) -> int | None:
        """SIGTERM, then SIGKILL if it does not stop in time; the exit code."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self._close_files()
        return self.proc.returncode

    def __enter__(self) -> ServeProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
