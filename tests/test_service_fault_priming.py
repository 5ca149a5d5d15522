"""A service fitted on a history primes its instrument-fault detectors on it (issue 39).

The detectors' references (a transmitter's noise, its daily changes) used to start at the
first live sample, while ``vfm evaluate``'s start at the file's first row: the service then
tested a young reference (on the walk's field, seed 4949, a false ``t_up`` drift two months
after the start that the study did not raise). Now a well fitted on the history feeds its
last 400 days to its detectors first. Shown here: a ``t_up`` frozen from day 100 of a
one-well field, with the service fitted on its first 120 days: before any live sample the
service already reports the fault open, from the start that ``vfm evaluate``'s detectors
give over the same rows; with detection off, nothing is fed or reported.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from http_support import http_get

from vfm_core.faults_sim import inject_fault
from vfm_core.observations import save_observations
from vfm_core.sensor_faults import faults_of_frame

pytestmark = pytest.mark.timeout(180)

WELL = "W01"


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    from vfm_core.simulate import simulate_field

    folder = tmp_path_factory.mktemp("fault_priming")
    obs = simulate_field(wells=1, years=0.6, seed=11).observations
    first = pd.to_datetime(obs["time"], utc=True).iloc[0]
    bad, truth = inject_fault(obs, WELL, "t_up", "frozen", first + pd.Timedelta(days=100), days=60)
    split = first + pd.Timedelta(days=120)
    before = bad[pd.to_datetime(bad["time"], utc=True) < split]
    return {
        "data": save_observations(bad, folder / "field.csv"),
        "split": str(split.date()),
        "truth": truth,
        "offline": faults_of_frame(before),
    }


def _view(folder: Path, field: dict[str, Any], enabled: bool) -> dict[str, Any]:
    from service.app import Service
    from service.testing import loopback_settings
    from service.transport import MemoryTransport

    model = {"name": "mm", "method": "ol", "history": str(field["data"])}
    model["history_until"] = field["split"]
    settings = loopback_settings(folder, model=model, sensor_faults={"enabled": enabled})
    service = Service(settings, MemoryTransport(settings.prefix))
    service.start()
    try:
        return http_get(service, f"/wells/{WELL}")
    finally:
        service.stop()


def test_a_fault_in_the_history_is_open_at_the_start(tmp_path: Path, field: dict[str, Any]) -> None:
    offline = [f for f in field["offline"] if f["sensor"] == "t_up" and f["kind"] == "frozen"]
    assert len(offline) == 1 and offline[0]["end"] is None  # the study's detectors, same rows
    view = _view(tmp_path / "on", field, enabled=True)
    found = [f for f in view["sensor_faults"] if f["sensor"] == "t_up" and f["kind"] == "frozen"]
    assert len(found) == 1, view["sensor_faults"]
    assert found[0]["end"] is None  # still open: the first live samples go on from it
    assert found[0]["start"] == offline[0]["start"]
    # from the last sample whose value it repeats (the sample before the first frozen row)
    began = pd.Timestamp(field["truth"]["start"])
    assert abs(pd.Timestamp(found[0]["start"]) - began) <= pd.Timedelta(days=7)
    assert _view(tmp_path / "off", field, enabled=False)["sensor_faults"] == []
