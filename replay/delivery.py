"""Whether everything a replay sent reached the service, and when it has all been answered.

A replay asks the service with a flush (:meth:`replay.client.FieldClient.flush`; the
service's side is :class:`service.transport.Flushes`): one before it sends anything (the
service's count of messages taken in, to start from) and one after its last message. Zenoh
delivers one session's messages in order, so the service's first answer to the last flush
says it has taken in everything sent before it, and its count tells how many messages came
in between: fewer than were sent means some were lost on the way. A service whose worker
takes the messages itself (the default) answers that flush a second time once it has
handled everything and published the answers, which reach the replay before that answer: the
replay then stops waiting at once instead of after ``--idle-timeout`` without an answer.

A service that answers no flushes (an instance that owns some wells only, ``zenoh.wells``)
leaves the replay waiting as before: until every sample is answered or none came for
``--idle-timeout`` s.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from tqdm import tqdm

from replay.client import FieldClient, FlushAnswer

__all__ = ["Delivery", "await_delivery", "start_count"]

#: how long the service may show no sign of life (no answer to the flush, no prediction)
#: before the replay stops waiting for it to take in the last messages, s
STALL_S = 120.0
#: after the service said it is done: how long the replay's own reader may take to hand on
#: the answers that arrived before that word, s
DRAIN_S = 0.5
#: without a sign of life for this long, the replay asks Zenoh whether the service still
#: subscribes to its keys (a service that stopped is told apart from a busy one), s
GONE_CHECK_S = 3.0


@dataclass
class Delivery:
    """What the service confirmed of a replay's messages."""

    #: messages the replay sent (samples, measurements, separator readings)
    sent: int
    #: the service's count of messages taken in grew by this between the two flushes (other
    #: senders' messages included); None where it did not answer
    taken_in: int | None = None
    #: the service said it had handled everything taken in before the last flush
    done: bool = False
    #: seconds waited for its answer after the last message
    waited_s: float = 0.0
    #: no service subscribed to the replay's keys any more while it waited (it stopped)
    gone: bool = False

    @property
    def lost(self) -> int:
        """Messages sent that the service did not take in (a lower bound with other senders)."""
        return 0 if self.taken_in is None else max(0, self.sent - self.taken_in)

    def line(self, stall_s: float = STALL_S) -> str:
        if self.gone:
            return (
                "The service went away while the replay waited for it (no subscriber to the "
                "replay's keys any more)"
                + (
                    f", after confirming {self.taken_in:,} of the {self.sent:,} messages sent."
                    if self.taken_in is not None
                    else f", before confirming the last of the {self.sent:,} messages sent."
                )
            )
        if self.taken_in is None:
            return (
                f"The service did not confirm taking in the last of the {self.sent:,} messages "
                f"sent within {stall_s:g} s without a sign of life (no answer to the replay's "
                "flush, no prediction): it may be stuck or gone; its GET /health 'received' "
                "tells how many it took in."
            )
        if self.lost:
            return (
                f"LOST: the service took in {self.taken_in:,} messages while the replay sent "
                f"{self.sent:,}: at least {self.lost:,} were lost between the two sessions "
                "(docs/guide/export-replay.md)."
            )
        handled = (
            ", and had handled them all when the replay stopped waiting"
            if self.done
            else " (it does not say when it has handled them: the replay waited for answers "
            "until none came for --idle-timeout)"
        )
        return f"The service confirmed taking in all {self.sent:,} messages sent{handled}."


def start_count(client: FieldClient, timeout: float) -> int | None:
    """The service's count of messages taken in before the replay sends anything (a flush
    and its first answer), or None when it answers no flushes within ``timeout`` s."""
    flush_id = client.flush(timeout)
    if flush_id is None:
        return None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        answers = client.flush_answers.get(flush_id) or []
        if answers:
            return answers[0].received
        time.sleep(0.02)
    return None


def await_delivery(
    client: FieldClient,
    expected: set[tuple[str, int]],
    *,
    sent: int,
    start: int,
    idle_timeout: float,
    final_timeout: float,
    stall_s: float = STALL_S,
    progress: bool = False,
) -> Delivery:
    """After the last message: flush, and wait for the service's word that it has taken in
    (and, where it says so, handled) everything, or until every ``expected`` sample is
    answered and the service has taken everything in; at most ``final_timeout`` s, and no
    longer than ``stall_s`` s without a sign of life from it. ``start``: its count of
    messages taken in before the replay (:func:`start_count`). ``progress``: a bar of the
    samples answered (the sending ends long before the answers on a busy service)."""
    began = time.monotonic()
    out = Delivery(sent=sent)
    flush_id = client.flush(stall_s)
    if flush_id is None:
        return out
    answers = client.flush_answers[flush_id]
    bar = tqdm(
        total=len(expected), unit="answer", desc="answers", disable=not progress, mininterval=0.5
    )
    with bar:
        _wait(client, expected, answers, out, bar, start, idle_timeout, final_timeout, stall_s)
    out.waited_s = time.monotonic() - began
    return out


def _wait(  # noqa: PLR0913 - the loop of await_delivery, its state handed in
    client: FieldClient,
    expected: set[tuple[str, int]],
    answers: list[FlushAnswer],
    out: Delivery,
    bar: tqdm,  # type: ignore[type-arg]
    start: int,
    idle_timeout: float,
    final_timeout: float,
    stall_s: float,
) -> None:
    began = time.monotonic()
    seen, sign = -1, began  # expected samples answered; when the service last showed life
    receipt_at: float | None = None
    checked = began  # when the replay last asked whether a service still subscribes
    counted, answered = -1, 0  # the client's count of answers when last looked through
    while (now := time.monotonic()) - began < final_timeout:
        if client.count != counted:  # (looking through every expected sample costs)
            counted = client.count
            answered = client.answered(expected)
        if answered != seen:
            bar.update(answered - max(seen, 0))
            seen, sign = answered, now
        if answers and receipt_at is None:
            receipt_at = sign = now
            out.taken_in = answers[0].received - start
        if any(a.done for a in answers):
            out.done = True
            _drain(client, expected)
            break
        if receipt_at is not None and answered == len(expected):
            # every sample answered; a service that will say when it is done may still be
            # handling the measurements: its word is waited for, --idle-timeout at most
            if not answers[0].reports_done or now - sign > idle_timeout:
                break
        if receipt_at is not None and not answers[0].reports_done:
            if now - sign > idle_timeout:  # no word will come: wait as before
                break
        elif now - sign > stall_s:
            break
        if now - max(sign, checked) > GONE_CHECK_S:
            checked = time.monotonic()
            if not client.service_present(timeout=1.0):
                out.gone = True
                break
        time.sleep(0.02)
    bar.update(client.answered(expected) - max(seen, 0))


def _drain(client: FieldClient, expected: set[tuple[str, int]]) -> None:
    """The answers published before the service's last word are on their way through the
    replay's own reader: wait until all expected are in or none came for :data:`DRAIN_S`."""
    seen, last = client.count, time.monotonic()
    while client.answered(expected) < len(expected) and time.monotonic() - last < DRAIN_S:
        time.sleep(0.01)
        if client.count != seen:
            seen, last = client.count, time.monotonic()
