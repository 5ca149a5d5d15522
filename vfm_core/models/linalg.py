"""Matrix products of the networks, through numpy's OpenBLAS where that is faster.

The networks' training steps are mostly products of a few hundred rows by 32 x 32 float64
weights per well (``WellMLP``, ``mtl``). Torch's CPU build runs them in MKL, which takes
its AVX2 code on AMD processors and spends more per call; numpy's OpenBLAS is faster on
these shapes. Measured on this project's machines (AMD EPYC, Zen 5, one thread),
``[10, 256, 32] x [10, 32, 32]``: torch ``bmm`` 165-180 us, numpy ``matmul`` 110 us with
the Haswell (AVX2) kernels these machines pin through ``OPENBLAS_CORETYPE``, 47 us with
OpenBLAS's AVX-512 kernels; ``benchmarks/bench_study.py --matmul torch,numpy`` compares
the study both ways on the machine at hand.

:func:`matmul` is the same product, in float64, either way: the numbers differ by rounding
only (a different order of the additions inside a dot product of 32 terms). It takes
numpy's path when

- no gradient has to flow through it (autograd keeps torch's path);
- both operands are float64 CPU tensors;
- the product is large enough: at least :data:`MIN_MACS` multiply-adds per matrix
  (below that, torch's smaller call overhead wins: 2.2 us against 3.3 us for one row
  by 32 x 32 per well; they break even near 8 rows).

OpenBLAS's threads are limited to torch's (one) by :func:`vfm_core.runtime.configure`.
``VFM_MATMUL=torch`` keeps every product in torch (for a comparison side by side).
"""

from __future__ import annotations

import os

import numpy as np
import torch

__all__ = ["MIN_MACS", "matmul", "numpy_enabled"]

#: multiply-adds per matrix of a product (N x K x M) from which numpy's path is taken
MIN_MACS = 8 * 32 * 32


def numpy_enabled() -> bool:
    """False when ``VFM_MATMUL=torch`` is set (read at each call: tests and benchmarks
    switch it)."""
    return os.environ.get("VFM_MATMUL", "").strip().lower() != "torch"


def _numpy_path(a: torch.Tensor, b: torch.Tensor, bias: torch.Tensor | None) -> bool:
    if a.dim() < 2 or b.dim() < 2 or a.shape[-2] * a.shape[-1] * b.shape[-1] < MIN_MACS:
        return False
    tensors = (a, b) if bias is None else (a, b, bias)
    if any(t.dtype != torch.float64 or t.device.type != "cpu" for t in tensors):
        return False
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return False
    return numpy_enabled()


def matmul(a: torch.Tensor, b: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``a @ b`` (+ ``bias``, broadcast), batched as :func:`torch.matmul` broadcasts.

    ``a`` [..., N, K], ``b`` [..., K, M]; ``bias`` broadcastable to the result."""
    if not _numpy_path(a, b, bias):
        if bias is None:
            return torch.matmul(a, b)
        if a.dim() == 3 and b.dim() == 3:
            return torch.baddbmm(bias, a, b)
        return torch.matmul(a, b) + bias
    out = np.matmul(a.detach().numpy(), b.detach().numpy())
    if bias is not None:
        np.add(out, bias.detach().numpy(), out=out)
    return torch.from_numpy(out)
