"""The process settings of vfm_core.runtime: glibc's malloc keeps a training step's memory.

Each check runs in a fresh interpreter: the settings apply once per process, at start."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

# a network's retrain on all its data each step (10 wells x about 750 samples), 60 steps;
# the minor page faults of a second retrain (the first warms the process up)
_RETRAIN = textwrap.dedent(
    """
    import json, os, resource
    # torch's training loop and products, as the models with effects run them (nn's own
    # loop is compiled and its products are numpy's: they allocate little either way)
    os.environ["VFM_FIT_KERNEL"] = "0"
    os.environ["VFM_MATMUL"] = "torch"
    from dataclasses import replace
    import numpy as np
    from vfm_core.runtime import configure, tune_malloc
    configure(1)
    from vfm_core.data import make_batch, target_mask
    from vfm_core.jobs.study import wells_of
    from vfm_core.learning import DEFAULT_TRAIN, fit_batch
    from vfm_core.models import make_model
    from vfm_core.observations import validate_frame
    from vfm_core.simulate import simulate_field
    frame = validate_frame(simulate_field(wells=10, years=1.0, seed=2).observations).frame
    wells = wells_of(frame)
    batch = make_batch(frame, wells, np.flatnonzero(target_mask(frame, "all")))
    model = make_model("nn", wells)
    train = replace(DEFAULT_TRAIN["nn"], early_stopping=False, max_iter=60, batch_size=0)
    fit_batch(model, batch, train)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    fit_batch(model, batch, train)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    print(json.dumps({"tuned": tune_malloc(), "faults": faults}))
    """
)


def _run(code: str, malloc: str | None) -> dict:
    env = dict(os.environ)
    env.pop("VFM_MALLOC", None)
    if malloc is not None:
        env["VFM_MALLOC"] = malloc
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])  # type: ignore[no-any-return]


def _glibc() -> bool:
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return False
    return sys.platform.startswith("linux") and hasattr(libc, "gnu_get_libc_version")


@pytest.mark.skipif(not _glibc(), reason="glibc's malloc settings apply on Linux with glibc only")
def test_training_memory_stays_in_the_process_unless_told_otherwise():
    """With the settings a retrain reuses its memory: almost no page is faulted in again
    (against hundreds of thousands with glibc's defaults, each one zeroed by the kernel);
    ``VFM_MALLOC=default`` leaves glibc's defaults."""
    tuned = _run(_RETRAIN, None)
    default = _run(_RETRAIN, "default")
    assert tuned["tuned"] is True and default["tuned"] is False
    if default["faults"] < 10_000:
        pytest.skip(
            f"glibc's defaults already keep this retrain's memory ({default['faults']} faults): "
            "nothing for the settings to show here"
        )
    assert tuned["faults"] < default["faults"] / 20, (tuned, default)


def test_the_vfm_command_takes_the_settings(tmp_path):
    """``vfm`` applies them at start (as ``vfm serve``, the tuning and diagnosis workers
    do): torch runs the threads asked for, and on glibc the malloc settings are in force."""
    out = tmp_path / "field.parquet"
    code = textwrap.dedent(
        f"""
        import json, torch
        from vfm_core import cli, runtime
        before = runtime._tuned
        rc = cli.main(["--threads", "1", "simulate", "--out", {str(out)!r}, "--wells", "1",
                       "--years", "0.2", "--quiet"])
        print(json.dumps({{"rc": rc, "before": before, "threads": torch.get_num_threads(),
                          "tuned": runtime._tuned}}))
        """
    )
    got = _run(code, None)
    assert got["rc"] == 0 and out.exists()
    assert got["before"] is None  # nothing set it before the command ran
    assert got["threads"] == 1
    assert got["tuned"] is _glibc()
