"""Scale-out: several ``vfm serve`` instances behind a Zenoh router, each owning a set of wells.

An instance owns the wells that match one of its ``zenoh.wells`` patterns: a well id in
which ``*`` stands for any run of characters (``W0*``, ``*-north``, ``W1*``; no pattern:
every well, as before). It subscribes only to its wells' key expressions, so the router
sends it nothing else (``<prefix>/W0$*/**``: Zenoh writes a wildcard inside a chunk as
``$*``); a message of another well that reaches it anyway (an in-memory transport, a
peer wired by hand) is refused as ``well of another instance``.

Every instance answers the Zenoh query ``<prefix>/@instances/*`` with a
:class:`InstanceClaim` (its Zenoh id, its patterns, its HTTP address); ``vfm instances``
lists them and an HTTP 404 for a well of another instance names the owner. A well must
never belong to two instances: the operator gives the instances disjoint patterns. At
start an instance declares its claim, then asks the network for the others' and refuses
to start (:class:`~vfm_core.errors.ConfigError`) when one that answers claims an
overlapping set. An instance that is dead (or not connected to this router) does not
answer, so the check does not see it; two instances started in the same instant both
see each other and both refuse.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from vfm_core.errors import ConfigError
from vfm_core.messages import WELL_ID_MAX, well_id_problem

__all__ = [
    "WellSet",
    "pattern_problem",
    "pattern_chunk",
    "overlapping",
    "InstanceClaim",
    "claims_key",
    "declare_claim",
    "list_instances",
    "check_no_overlap",
    "owner_sentence",
]

logger = logging.getLogger("vfm.service.scaleout")


def pattern_problem(pattern: str) -> str | None:
    """Why ``pattern`` cannot be a well pattern, as a sentence; None when it can."""
    if not pattern or pattern.strip() != pattern:
        return (
            f"The well pattern {pattern!r} is empty or has spaces around it; write a well id "
            "with * for any characters, e.g. W0*."
        )
    if well_id_problem(pattern.replace("*", "x")) is not None:
        return (
            f"The well pattern {pattern[: WELL_ID_MAX + 8]!r} is not a well id in which * stands "
            f"for any characters (printable, at most {WELL_ID_MAX} characters, no '/', '$', '?', "
            "'#'); write it like W0* or *-north."
        )
    return None


def _collapse(pattern: str) -> str:
    return re.sub(r"\*+", "*", pattern)


def pattern_chunk(pattern: str) -> str:
    """The Zenoh key-expression chunk of a well pattern: ``*`` alone, else each ``*`` as ``$*``."""
    pattern = _collapse(pattern)
    return "*" if pattern == "*" else pattern.replace("*", "$*")


def overlapping(a: Sequence[str], b: Sequence[str]) -> tuple[str, str] | None:
    """A pair of patterns, one of ``a`` and one of ``b``, that a well id can match both; None
    when the sets are disjoint. An empty sequence means every well."""
    import zenoh

    a, b = list(a) or ["*"], list(b) or ["*"]
    for pa in a:
        ka = zenoh.KeyExpr(pattern_chunk(pa))
        for pb in b:
            if ka.intersects(zenoh.KeyExpr(pattern_chunk(pb))):
                return pa, pb
    return None


class WellSet:
    """The wells an instance owns: those matching one of ``patterns`` (none: every well)."""

    def __init__(self, patterns: Sequence[str]) -> None:
        self.patterns = [_collapse(p) for p in patterns]
        self._regex = (
            re.compile("|".join(re.escape(p).replace(r"\*", ".*") for p in self.patterns))
            if self.patterns
            else None
        )

    @property
    def everything(self) -> bool:
        return self._regex is None

    def __contains__(self, well: str) -> bool:
        return self._regex is None or self._regex.fullmatch(well) is not None

    def key_exprs(self, prefix: str) -> list[str]:
        """The subscriber key expressions: ``<prefix>/**`` for every well, else one per pattern."""
        if self._regex is None:
            return [f"{prefix}/**"]
        return [f"{prefix}/{pattern_chunk(p)}/**" for p in self.patterns]

    def describe(self) -> str:
        """``W0*,W1*``, or ``*`` for every well (the ready line's ``owns=``)."""
        return ",".join(self.patterns) or "*"


@dataclass
class InstanceClaim:
    """What an instance answers on ``<prefix>/@instances/<zid>``."""

    zid: str
    prefix: str
    wells: list[str]  # the patterns; empty: every well
    http: str | None = None
    locators: list[str] = field(default_factory=list)
    started_at: float = 0.0

    def to_json(self) -> bytes:
        return json.dumps(asdict(self)).encode()

    @classmethod
    def from_json(cls, payload: bytes) -> InstanceClaim | None:
        try:
            data = json.loads(payload)
            return cls(
                zid=str(data["zid"]),
                prefix=str(data["prefix"]),
                wells=[str(w) for w in data["wells"]],
                http=None if data.get("http") is None else str(data["http"]),
                locators=[str(x) for x in data.get("locators", [])],
                started_at=float(data.get("started_at", 0.0)),
            )
        except (ValueError, KeyError, TypeError):
            return None

    def owns(self, well: str) -> bool:
        return well in WellSet(self.wells)


def claims_key(prefix: str, zid: str = "*") -> str:
    """``<prefix>/@instances/<zid>`` (``@`` chunks are never matched by ``*``/``**``, so the
    claims never reach a sample subscriber)."""
    return f"{prefix}/@instances/{zid}"


def declare_claim(session: Any, prefix: str, claim: Callable[[], InstanceClaim]) -> Any:
    """Answer ``<prefix>/@instances/*`` with ``claim()`` (read at each query); returns the
    queryable (undeclared with the session)."""
    key = claims_key(prefix, str(session.zid()))

    def answer(query: Any) -> None:
        with query:
            query.reply(key, claim().to_json())

    return session.declare_queryable(key, answer)


def list_instances(session: Any, prefix: str, timeout: float = 2.0) -> list[InstanceClaim]:
    """The claims of every instance under ``prefix`` that answers within ``timeout`` s."""
    import zenoh

    found: list[InstanceClaim] = []
    for reply in session.get(
        claims_key(prefix),
        timeout=timeout,
        consolidation=zenoh.ConsolidationMode.NONE,  # one reply per instance, not per key
    ):
        if reply.ok is None:
            continue
        claim = InstanceClaim.from_json(reply.ok.payload.to_bytes())
        if claim is not None:
            found.append(claim)
    return sorted(found, key=lambda c: (c.wells, c.zid))


def check_no_overlap(session: Any, prefix: str, wells: Sequence[str], timeout: float) -> None:
    """Raise :class:`ConfigError` when another instance that answers claims a well of ours."""
    me = str(session.zid())
    for other in list_instances(session, prefix, timeout):
        if other.zid == me:
            continue
        pair = overlapping(wells, other.wells)
        if pair is not None:
            where = other.http or ", ".join(other.locators) or f"Zenoh id {other.zid}"
            raise ConfigError(
                f"Another instance ({where}) already owns wells under '{prefix}' that this one "
                f"would own too: its pattern '{pair[1]}' and this one's '{pair[0]}' match the same "
                "well ids (no zenoh.wells means every well). A well must belong to one instance: "
                "give each instance a disjoint zenoh.wells (e.g. ['W0*'] and ['W1*'])."
            )


class _OwnerCache:
    """The claims of the network, asked at most once a second (HTTP 404 answers read them)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._at = 0.0
        self._of: tuple[str, str] = ("", "")
        self._claims: list[InstanceClaim] = []

    def claims(self, session: Any, prefix: str) -> list[InstanceClaim]:
        of = (str(session.zid()), prefix)
        with self._lock:
            if of != self._of or time.monotonic() - self._at > 1.0:
                try:
                    self._claims = list_instances(session, prefix, timeout=1.0)
                except Exception:  # the network is only a hint here
                    logger.debug("Listing the instances failed.", exc_info=True)
                    self._claims = []
                self._at, self._of = time.monotonic(), of
            return list(self._claims)


_OWNERS = _OwnerCache()


def owner_sentence(session: Any | None, prefix: str, own: WellSet, well: str) -> str | None:
    """For a well outside ``own``: a sentence naming the instance that owns it (if one
    answers); None when the well is one of ours (the ordinary 404 applies)."""
    if well in own:
        return None
    mine = own.describe()
    head = f"The well '{well}' is not served by this instance, which owns the wells {mine}"
    if session is not None:
        me = str(session.zid())
        for claim in _OWNERS.claims(session, prefix):
            if claim.zid != me and claim.owns(well):
                where = claim.http or "an instance without HTTP yet"
                return (
                    f"{head}; the instance that owns {', '.join(claim.wells) or '*'} serves it: "
                    f"{where}/wells/{well}."
                )
    return (
        f"{head}; no running instance on this Zenoh network claims it (`vfm instances "
        "--connect <router>` lists the instances and their wells)."
    )
