"""The store's multi-row sample inserts: a batch's samples in statements of many rows."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.store import InsertSample, Store

pytestmark = pytest.mark.timeout(60)

INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


def _sample(well: str, t: int, q: float) -> InsertSample:
    return InsertSample(well, t, INPUTS, t, q, 0.1 * q, 0.6 * q, 0.3 * q, 1)


@pytest.mark.parametrize("rows", [1, 2, 63, 64, 65, 200, 1000])
def test_multi_row_inserts_store_what_one_by_one_stores(tmp_path: Path, rows: int) -> None:
    """A batch's samples go in as multi-row statements; a sample already stored is
    ignored alone (INSERT OR IGNORE per row), and the count is of the rows written."""
    many = Store(tmp_path / "many.sqlite", "normal")
    one = Store(tmp_path / "one.sqlite", "normal")
    try:
        ops = [_sample(f"W{i % 7:02d}", 1000 + i, float(i)) for i in range(rows)]
        again = ops[: rows // 2]  # already stored: ignored
        many.write(again)
        for op in again:
            one.write([op])
        assert many.write(ops) == rows - len(again)
        for op in ops:
            one.write([op])
        for well in {op.well for op in ops}:
            assert many.history(well, 0, 2**62, 10_000) == one.history(well, 0, 2**62, 10_000)
    finally:
        many.close()
        one.close()
