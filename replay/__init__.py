"""Replay observation files through a running service over Zenoh, and the ``vfm demo``.

Public surface: :func:`replay_frame` and :class:`ReplayResult` (from ``replay.replayer``,
imported lazily so that ``vfm --help`` stays fast). This package talks to the service
only over Zenoh; only ``replay.demo`` starts one.
"""

from typing import Any

__all__ = ["ReplayError", "ReplayResult", "replay_frame"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from replay import replayer

        return getattr(replayer, name)
    raise AttributeError(f"module 'replay' has no attribute {name!r}")
