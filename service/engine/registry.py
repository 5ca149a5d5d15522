"""Which wells the engine holds, which are being created, which are retired; who may enter.

:meth:`Registry.admit` runs on the receiving side (the transport's receiver thread, an
HTTP thread) before a message is queued, and is cheap: a well already known passes; a
retired one is refused (``retired well``); a new one is refused over HTTP (``unknown
well``: HTTP never creates a well), with ``inputs.unknown_wells = "reject"``, when the
service already holds ``inputs.max_wells`` wells (``too many wells``) or when new wells
appear faster than ``inputs.new_wells_per_s`` (``too many new wells``); otherwise it is
marked as being created. The well's worker then builds its learner when it takes the
first message (:meth:`Registry.created`), so no model is built on the receiver thread.

With ``inputs.well_rate_hz`` set, :meth:`Registry.quota` also holds each well to that
many messages a second (a token bucket of ``inputs.well_burst``): above it a message is
refused as ``well flooding``.
"""

from __future__ import annotations

import threading
import time

from service.config import Settings
from service.engine.state import WellState
from service.errors import InvalidRequest, UnknownWell

__all__ = ["Registry", "TokenBucket"]


class TokenBucket:
    """``rate`` tokens a second, at most ``burst`` saved up (not thread-safe: callers lock)."""

    __slots__ = ("rate", "burst", "tokens", "stamp")

    def __init__(self, rate: float, burst: int) -> None:
        self.rate = rate
        self.burst = float(burst)
        self.tokens = float(burst)
        self.stamp = time.monotonic()

    def spent(self, now: float | None = None) -> bool:
        """Whether no message would pass now (less than one token saved), taking none."""
        now = time.monotonic() if now is None else now
        return min(self.burst, self.tokens + (now - self.stamp) * self.rate) < min(1.0, self.burst)

    def take(self, now: float | None = None, n: float = 1.0) -> bool:
        """Take ``n`` tokens. More than ``burst`` pass once the burst is saved up, and the
        balance goes below zero: the well repays them before it sends again."""
        now = time.monotonic() if now is None else now
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= min(n, self.burst):
            self.tokens -= n
            return True
        return False


class Registry:
    """The wells of the engine and the rules for new ones; see the module docstring."""

    def __init__(self, settings: Settings, wells: dict[str, WellState]) -> None:
        self.settings = settings
        self.wells = wells
        self.creating: set[str] = set()
        #: retired wells (kept data) -> when they were retired (epoch ns)
        self.retired: dict[str, int] = {}
        self._lock = threading.Lock()
        i = settings.inputs
        self._new = TokenBucket(i.new_wells_per_s, i.new_wells_burst)
        self._quotas: dict[str, TokenBucket] = {}

    def admit(self, well: str, *, create: bool = True) -> None:
        """Let the well's messages be queued, or raise the refusal (see the module docstring)."""
        if well in self.wells:
            return
        inputs = self.settings.inputs
        with self._lock:
            if well in self.retired:
                raise InvalidRequest(
                    f"The well {well} was retired (DELETE /wells/{well}); its messages are refused. "
                    f"DELETE /wells/{well}?purge=true removes its data so that the id can be used again.",
                    "retired well",
                )
            if well in self.wells or well in self.creating:
                return
            if not create:
                raise UnknownWell(
                    f"The well {well} is not known to this service, and HTTP never creates a well "
                    "(a typo would make a phantom one); GET /wells lists the wells. A new well "
                    "appears with its first sensor sample over Zenoh, or from inputs.wells.",
                    "unknown well",
                )
            if inputs.unknown_wells == "reject":
                raise UnknownWell(
                    f"The well {well} is not known to this service; add it to inputs.wells or set "
                    "inputs.unknown_wells = 'create'.",
                    "unknown well",
                )
            if len(self.wells) + len(self.creating) >= inputs.max_wells:
                raise InvalidRequest(
                    f"The well {well} is not created: the service holds {inputs.max_wells} wells "
                    "(inputs.max_wells). Retire wells no longer in use (DELETE /wells/{well}) or "
                    "raise inputs.max_wells.",
                    "too many wells",
                )
            if not self._new.take():
                raise InvalidRequest(
                    f"The well {well} is not created now: new wells appear faster than "
                    f"{inputs.new_wells_per_s:g} a second (inputs.new_wells_per_s); its messages "
                    "are accepted once the rate allows. Check the sender's well ids.",
                    "too many new wells",
                )
            self.creating.add(well)

    def quota_spent(self, well: str) -> None:
        """With ``inputs.well_rate_hz`` set: refuse any message of a well whose quota is
        spent, before it is decoded (a flood of large sensor blocks then costs the receiver
        a lookup per message, not their parsing, so it cannot delay the other wells); takes
        nothing: :meth:`quota` counts the message once it is parsed."""
        if self.settings.inputs.well_rate_hz <= 0:
            return
        with self._lock:
            bucket = self._quotas.get(well)
            spent = bucket is not None and bucket.spent()
        if spent:
            self._refuse(well, 1)

    def _refuse(self, well: str, samples: int) -> None:
        rate = self.settings.inputs.well_rate_hz
        what = "message" if samples == 1 else f"sensor block of {samples} samples"
        raise InvalidRequest(
            f"The well {well} sends more than {rate:g} messages a second (inputs.well_rate_hz, "
            f"burst {self.settings.inputs.well_burst}; a sensor block counts its samples); "
            f"this {what} is refused so that other wells are not delayed. Slow the sender down.",
            "well flooding",
        )

    def quota(self, well: str, samples: int = 1) -> None:
        """With ``inputs.well_rate_hz`` set: refuse a message above the well's rate. A
        sensor block counts its samples (at most the burst), so blocks do not widen it."""
        rate = self.settings.inputs.well_rate_hz
        if rate <= 0:
            return
        with self._lock:
            bucket = self._quotas.get(well)
            if bucket is None:
                bucket = self._quotas[well] = TokenBucket(rate, self.settings.inputs.well_burst)
            ok = bucket.take(n=samples)
        if not ok:
            self._refuse(well, samples)

    def known(self, well: str) -> bool:
        """Whether ``well`` is served (or being created): its refusals are counted per well."""
        return well in self.wells or well in self.creating

    def expected(self, well: str) -> bool:
        """Whether a message of ``well`` may create it on its worker (it was admitted as new)."""
        with self._lock:
            return well in self.creating

    def created(self, well: str, st: WellState) -> None:
        """The well's worker built it: it is known from now on."""
        with self._lock:
            self.wells[well] = st
            self.creating.discard(well)

    def abandon(self, well: str) -> None:
        """A new well's first message was not queued after all: it is not being created."""
        with self._lock:
            self.creating.discard(well)

    def is_retired(self, well: str) -> bool:
        with self._lock:
            return well in self.retired

    def retiring(self, well: str, when_ns: int) -> None:
        """Refuse the well's messages from now on (its worker retires it next)."""
        with self._lock:
            self.retired[well] = when_ns
            self.creating.discard(well)

    def retired_done(self, well: str, purged: bool) -> None:
        """The worker retired the well; a purged one's id is free again."""
        with self._lock:
            self.wells.pop(well, None)
            self._quotas.pop(well, None)
            if purged:
                self.retired.pop(well, None)

    def unretire(self, well: str) -> None:
        """Undo :meth:`retiring` (the retirement could not run)."""
        with self._lock:
            self.retired.pop(well, None)
