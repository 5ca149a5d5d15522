"""Writing files so that a crash or Ctrl-C never leaves a half-written one.

Every output of the VFM (observation files, models, metrics, reports) is written to a
temporary file beside its destination and moved into place with one ``os.replace``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "write_text_atomic", "write_bytes_atomic", "write_with", "staging_dir"]


@contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside ``path``; on success it is flushed to disk and replaces
    ``path``, on error it is removed. Parent folders are created."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
    os.close(fd)
    temp = Path(name)
    # mkstemp makes the file private (0600); an output file gets the usual permissions
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(temp, 0o666 & ~umask)
    try:
        yield temp
        with open(temp, "rb+") as handle:  # on disk before it takes the final name
            os.fsync(handle.fileno())
        os.replace(temp, final)
    finally:
        temp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    with atomic_path(path) as temp:
        temp.write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> Path:
    with atomic_path(path) as temp:
        temp.write_bytes(data)
    return Path(path)


def write_with(path: str | os.PathLike[str], writer: Callable[[Path], object]) -> Path:
    """Call ``writer(temp_path)`` and move the result to ``path`` (e.g. ``frame.to_parquet``)."""
    with atomic_path(path) as temp:
        writer(temp)
    return Path(path)


@contextmanager
def staging_dir(out_dir: str | os.PathLike[str]) -> Iterator[Path]:
    """A staging folder inside ``out_dir``: files written there are moved into ``out_dir`` on
    success (each with ``os.replace``); on error nothing half-written reaches ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        yield staging
        for f in sorted(staging.iterdir()):
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
