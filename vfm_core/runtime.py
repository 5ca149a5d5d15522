"""The process's run-time settings for the VFM's workload: torch threads and glibc's malloc.

:func:`configure` runs once at the start of every command (``vfm``'s CLI, ``vfm serve``,
the tuning workers, the benchmarks), before the work allocates anything large.

**Torch's intra-op threads**: one by default. The VFM's tensors are small (wells x
samples): a second thread buys nothing and, on a machine shared with other work, its
barriers cost an order of magnitude (measured: a study 10x slower with 2 threads under
load).

**glibc's malloc** (Linux): a network's training step allocates and frees tensors of a
few hundred kilobytes, thousands of times a second. With glibc's defaults each of them
is taken from the operating system and handed back (the heap's top is trimmed, larger
blocks are mapped and unmapped), and every page is faulted in and zeroed again: an
element-wise ReLU on 80,000 numbers took 200 us in a retrain against 23 us on memory
already in use. Two ``mallopt`` settings keep that memory in the process for the next
step: a 64 MiB pad at the heap's top (``M_TOP_PAD``) and a fixed 32 MiB threshold below
which blocks come from the heap, not from their own mapping (``M_MMAP_THRESHOLD``). It
is the in-process form of the advice to run PyTorch on CPU with another allocator
(tcmalloc, jemalloc) preloaded, which a ``pip install`` cannot arrange. The peak memory
stays the same (it is held a little longer); ``VFM_MALLOC=default`` leaves glibc's
settings alone, and on another C library, or another system, nothing is changed.

**numpy's BLAS threads** (:mod:`vfm_core.models.linalg` runs the networks' products in
numpy's OpenBLAS): limited to torch's, for the same reason.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

__all__ = [
    "configure",
    "torch_threads",
    "blas_threads",
    "tune_malloc",
    "MALLOC_SETTINGS",
]

logger = logging.getLogger("vfm.runtime")

#: glibc's ``mallopt`` parameters (malloc.h) and the values set
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
MALLOC_SETTINGS: dict[str, int] = {"M_TOP_PAD": 64 << 20, "M_MMAP_THRESHOLD": 32 << 20}
_CODES = {"M_TOP_PAD": _M_TOP_PAD, "M_MMAP_THRESHOLD": _M_MMAP_THRESHOLD}

_tuned: bool | None = None


def torch_threads(threads: int = 1) -> None:
    """Torch's intra-op threads (at least one; see the module docstring)."""
    import torch

    torch.set_num_threads(max(1, int(threads)))


def tune_malloc() -> bool:
    """Apply :data:`MALLOC_SETTINGS` with glibc's ``mallopt`` (once per process); True when
    they are in force. ``VFM_MALLOC=default`` (or any other C library) changes nothing."""
    global _tuned
    if _tuned is not None:
        return _tuned
    _tuned = False
    if os.environ.get("VFM_MALLOC", "").strip().lower() in {"default", "0", "off"}:
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        if not hasattr(libc, "gnu_get_libc_version"):  # musl and others: not glibc's knobs
            return False
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    applied = [name for name, value in MALLOC_SETTINGS.items() if mallopt(_CODES[name], value) == 1]
    if len(applied) != len(MALLOC_SETTINGS):
        logger.info("glibc's malloc took only %s of %s.", applied, sorted(MALLOC_SETTINGS))
    _tuned = bool(applied)
    return _tuned


def blas_threads(threads: int = 1) -> None:
    """numpy's and scipy's BLAS threads (OpenBLAS's pools, through threadpoolctl), at least
    one. threadpoolctl limits the libraries loaded, so scipy's (which the compiled
    kernels' ``np.dot`` calls) is loaded first."""
    import scipy.linalg  # noqa: F401 - loads scipy's BLAS, to be limited too
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=max(1, int(threads)), user_api="blas")


def configure(threads: int = 1) -> None:
    """The settings of the module docstring: torch's threads, numpy's BLAS threads, then
    glibc's malloc."""
    tune_malloc()
    torch_threads(threads)
    blas_threads(threads)
