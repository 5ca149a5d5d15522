"""The field side: replay observation files through a running service, and the ``vfm demo``.

Public surface: :func:`replay_frame` and :class:`ReplayResult` (from ``replay.replayer``,
imported lazily so that ``vfm --help`` stays fast), and the field client that sends a
field's inputs and collects the predictions (``replay.client.FieldClient``, shared by the
replay, the benchmark and the tests). This package talks to the service only through a
bus (Zenoh, or the service's in-memory transport); only ``replay.demo`` starts a service.
"""

from typing import Any

__all__ = ["ReplayError", "ReplayResult", "replay_frame"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from replay import replayer

        return getattr(replayer, name)
    raise AttributeError(f"module 'replay' has no attribute {name!r}")
