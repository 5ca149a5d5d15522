"""The networks' products through numpy's OpenBLAS (vfm_core.models.linalg)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vfm_core.models import linalg
from vfm_core.models.linalg import matmul
from vfm_core.runtime import blas_threads


def _operands(rows: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(4, rows, 32, generator=g, dtype=torch.float64)
    b = torch.randn(4, 32, 32, generator=g, dtype=torch.float64)
    bias = torch.randn(4, 1, 32, generator=g, dtype=torch.float64)
    return a, b, bias


def test_large_products_take_numpy_and_equal_torch_to_rounding() -> None:
    a, b, bias = _operands(256)
    out = matmul(a, b, bias)
    expected = torch.baddbmm(bias, a, b)
    assert linalg._numpy_path(a, b, bias)
    assert out.dtype == torch.float64 and out.shape == (4, 256, 32)
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    # transposed operands (the pullback's z^T delta) and a shared 2-D weight (mtl)
    d = torch.randn(4, 256, 32, dtype=torch.float64)
    torch.testing.assert_close(matmul(a.transpose(1, 2), d), torch.bmm(a.transpose(1, 2), d))
    torch.testing.assert_close(matmul(a, b[0], bias[0, 0]), a @ b[0] + bias[0, 0])


def test_small_products_autograd_and_float32_stay_in_torch() -> None:
    a, b, bias = _operands(1)
    assert not linalg._numpy_path(a, b, bias)  # one row per well: torch's call is cheaper
    assert torch.equal(matmul(a, b, bias), torch.baddbmm(bias, a, b))
    big, w, bias = _operands(256)
    w.requires_grad_(True)
    out = matmul(big, w, bias)  # a gradient flows through w: torch's path, with its graph
    assert out.requires_grad
    out.sum().backward()
    # d sum(a w) / d w[k, j] = sum_i a[i, k]
    torch.testing.assert_close(w.grad, big.sum(1).unsqueeze(-1).expand(-1, -1, 32))
    with torch.no_grad():  # no graph wanted: numpy's path even for a parameter
        assert linalg._numpy_path(big, w, bias)
    assert not linalg._numpy_path(big.float(), w.detach().float(), None)


def test_vfm_matmul_torch_switches_numpy_off(monkeypatch: pytest.MonkeyPatch) -> None:
    a, b, bias = _operands(256)
    monkeypatch.setenv("VFM_MATMUL", "torch")
    assert not linalg._numpy_path(a, b, bias)
    assert torch.equal(matmul(a, b, bias), torch.baddbmm(bias, a, b))


def test_blas_threads_limits_numpys_pool() -> None:
    from threadpoolctl import threadpool_info, threadpool_limits

    with threadpool_limits(limits=None):  # restored after the test
        blas_threads(1)
        pools = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert pools and all(p["num_threads"] == 1 for p in pools)
    assert np.matmul(np.ones((2, 2)), np.ones((2, 2)))[0, 0] == 2.0
