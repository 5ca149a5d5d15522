"""A well whose model never moves while its measured rate does: the residual alarm's tests.

The well ``W01`` runs ``mm`` with a retrain period longer than the data (``pbl:3650d``):
fitted on its first measurement, it predicts the same rate at the same inputs until the end,
so its residuals are the meter's own scatter until the measured rate moves (a change the
model does not follow). :func:`fixed_model_service` runs the service on the in-memory
transport (with its HTTP API on a loopback port when asked); :func:`send_readings` sends the
well's samples and MPFM readings.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from replay.client import FieldClient, sample_of
from service.app import Service, running
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.messages import Measurement

__all__ = ["INPUTS", "T0", "fixed_model_service", "send_readings", "wait_learned"]

T0 = datetime(2021, 5, 1, 0, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


@contextmanager
def fixed_model_service(
    folder: Path, *, http: bool = False, token: str | None = None, **overrides: Any
) -> Iterator[tuple[Service, FieldClient]]:
    """The service (``mm`` + ``pbl:3650d``, store in ``folder``, settings ``overrides``) and a
    field client on its bus, once it listens to ``W01``; with ``http`` its HTTP API runs on a
    loopback port (``service.http_url``), its mutating endpoints behind ``token`` if given."""
    if token is not None:
        overrides["http"] = {"token": token}
    settings = loopback_settings(folder, model={"name": "mm", "method": "pbl:3650d"}, **overrides)
    bus = MemoryTransport(settings.prefix)
    with ExitStack() as stack:
        if http:
            service = stack.enter_context(running(settings, bus)).service
        else:
            service = Service(settings, bus)
            service.start()
            stack.callback(service.stop)
        client = stack.enter_context(FieldClient(bus, settings.prefix))
        client.wait_for_service("W01")
        yield service, client


def send_readings(
    client: FieldClient,
    level: Callable[[int], float],
    days: int,
    seed: int,
    *,
    noise: float = 0.03,
    inputs: tuple[float, ...] = INPUTS,
    choke_spread: float = 0.0,
    start: datetime = T0,
) -> list[datetime]:
    """``W01``'s samples and MPFM readings, two a day (3 and 15 hours after each midnight
    from ``start``, :data:`T0` by default) for ``days`` days: the reading is
    ``1000 * level(day)`` Sm3/h (``day`` counted from :data:`T0`) times a log-normal error of
    sd ``noise``. The samples carry ``inputs``, their choke (fraction) drawn uniformly from
    ``choke_spread`` above it (from a generator of its own: the readings' errors are the same
    with or without it). Returns the times sent."""
    rng = np.random.default_rng(seed)
    chokes = np.random.default_rng(seed + 1).uniform(0.0, choke_spread, 2 * days)
    times = [start + timedelta(hours=12 * i + 3) for i in range(2 * days)]
    for i, t in enumerate(times):
        q = 1000.0 * level((t - T0).days) * float(np.exp(noise * rng.standard_normal()))
        sample = (inputs[0] + float(chokes[i]), *inputs[1:])
        client.send_sample("W01", sample_of(t, sample))
        client.send_measurement("W01", "mpfm", Measurement(time=t, q_total=q))
    return times


def wait_learned(service: Service, count: int, timeout_s: float = 60) -> None:
    """Wait until ``W01`` has ``count`` measurements stored, every one learned."""
    store = service.store
    assert store is not None

    def learned() -> bool:
        rows = store.history("W01", 0, 2**62, 10_000)[1]
        return len(rows) == count and all(m.status == "learned" for m in rows)

    wait_until(learned, timeout_s, "every measurement to be learned")
