"""Tests of the Volve conversion.

The synthetic frames here are made-up numbers in Volve's column layout, checked by hand.
The real file is licensed: it is read from ../shared beside the repository, never copied.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vfm_core import schema
from vfm_core.errors import DataError
from vfm_core.observations import load_observations
from vfm_core.volve import (
    MIN_ON_STREAM_HOURS,
    NEEDED_COLUMNS,
    REMOVAL_REASONS,
    RHO_GAS_SC,
    RHO_OIL,
    RHO_WAT,
    convert_volve,
    field_notes,
    import_volve,
    read_volve_csv,
)

VOLVE_CSV = Path(__file__).parents[2] / "shared" / "data" / "volve" / "volve_daily_production.csv"

ATM = 1.01325  # bar, written out to check the gauge -> absolute step by hand

# Volve's header, in its order.
HEADER = (
    "DATEPRD,WELL_BORE_CODE,NPD_WELL_BORE_CODE,NPD_WELL_BORE_NAME,NPD_FIELD_CODE,NPD_FIELD_NAME,"
    "NPD_FACILITY_CODE,NPD_FACILITY_NAME,ON_STREAM_HRS,AVG_DOWNHOLE_PRESSURE,"
    "AVG_DOWNHOLE_TEMPERATURE,AVG_DP_TUBING,AVG_ANNULUS_PRESS,AVG_CHOKE_SIZE_P,AVG_CHOKE_UOM,"
    "AVG_WHP_P,AVG_WHT_P,DP_CHOKE_SIZE,BORE_OIL_VOL,BORE_GAS_VOL,BORE_WAT_VOL,BORE_WI_VOL,"
    "FLOW_KIND,WELL_TYPE"
).split(",")

# A made-up good producing day: 24 h, 50 % choke, 40 bar(g) WHP, 10 bar drop, 70 degC.
BASE = {
    "DATEPRD": "05-Mar-15",
    "WELL_BORE_CODE": "NO X-A",
    "NPD_WELL_BORE_CODE": 1,
    "NPD_WELL_BORE_NAME": "X-A",
    "NPD_FIELD_CODE": 2,
    "NPD_FIELD_NAME": "TESTFIELD",
    "NPD_FACILITY_CODE": 3,
    "NPD_FACILITY_NAME": "RIG",
    "ON_STREAM_HRS": 24.0,
    "AVG_DOWNHOLE_PRESSURE": 200.0,
    "AVG_DOWNHOLE_TEMPERATURE": 100.0,
    "AVG_DP_TUBING": 150.0,
    "AVG_ANNULUS_PRESS": 10.0,
    "AVG_CHOKE_SIZE_P": 50.0,
    "AVG_CHOKE_UOM": "%",
    "AVG_WHP_P": 40.0,
    "AVG_WHT_P": 70.0,
    "DP_CHOKE_SIZE": 10.0,
    "BORE_OIL_VOL": 240.0,
    "BORE_GAS_VOL": 0.0,
    "BORE_WAT_VOL": 480.0,
    "BORE_WI_VOL": np.nan,
    "FLOW_KIND": "production",
    "WELL_TYPE": "OP",
}

# (overrides of BASE, the removal reason it should be counted under or None if kept)
CASES: list[tuple[dict[str, object], str | None]] = [
    ({}, None),
    (
        {
            "DATEPRD": "26-Oct-14",
            "NPD_WELL_BORE_NAME": "X-B",
            "ON_STREAM_HRS": 25.0,
            "AVG_CHOKE_SIZE_P": 100.0,
            "AVG_WHP_P": 30.0,
            "DP_CHOKE_SIZE": 2.0,
            "BORE_OIL_VOL": 100.0,
            "BORE_GAS_VOL": 15000.0,
            "BORE_WAT_VOL": 0.0,
        },
        None,
    ),
    ({"WELL_TYPE": "WI"}, "not a producer"),
    ({"FLOW_KIND": "injection", "WELL_TYPE": "WI"}, "not a producer"),
    ({"DATEPRD": "2015-03-06"}, "no usable date or well"),
    ({"DATEPRD": "06-Mar-15", "NPD_WELL_BORE_NAME": np.nan}, "no usable date or well"),
    ({"DATEPRD": "07-Mar-15", "ON_STREAM_HRS": 23.8}, "not a full producing day"),
    ({"DATEPRD": "08-Mar-15", "ON_STREAM_HRS": np.nan}, "not a full producing day"),
    ({"DATEPRD": "09-Mar-15", "ON_STREAM_HRS": 26.0}, "ON_STREAM_HRS above 25"),
    ({"DATEPRD": "10-Mar-15", "AVG_WHT_P": np.nan}, "missing choke/pressure/temperature"),
    ({"DATEPRD": "11-Mar-15", "DP_CHOKE_SIZE": np.nan}, "missing choke/pressure/temperature"),
    ({"DATEPRD": "12-Mar-15", "AVG_CHOKE_SIZE_P": 0.0}, "choke, wellhead pressure"),
    ({"DATEPRD": "13-Mar-15", "AVG_WHP_P": -1.0}, "choke, wellhead pressure"),
    ({"DATEPRD": "14-Mar-15", "AVG_CHOKE_SIZE_P": 100.5}, "choke outside 0..1"),
    ({"DATEPRD": "15-Mar-15", "BORE_WAT_VOL": np.nan}, "missing produced volume"),
    ({"DATEPRD": "16-Mar-15", "BORE_WAT_VOL": -3.0}, "negative produced volume"),
    (
        {"DATEPRD": "17-Mar-15", "BORE_OIL_VOL": 0.0, "BORE_GAS_VOL": 0.0, "BORE_WAT_VOL": 0.0},
        "no produced volume",
    ),
    ({"DATEPRD": "18-Mar-15", "AVG_WHP_P": 1.0, "DP_CHOKE_SIZE": 2.5}, "p_down <= 0"),
    ({"DATEPRD": "19-Mar-15", "DP_CHOKE_SIZE": 0.0}, "p_down >= p_up"),
    ({"DATEPRD": "20-Mar-15", "DP_CHOKE_SIZE": -0.5}, "p_down >= p_up"),
    ({"BORE_OIL_VOL": 999.0}, "duplicate well and day"),  # same day and well as the first
]


def synthetic_raw() -> pd.DataFrame:
    return pd.DataFrame([{**BASE, **overrides} for overrides, _ in CASES], columns=HEADER)


def frame_q_total() -> pd.Series:
    return convert_volve(synthetic_raw())[0]["q_total"]


def reason_named(prefix: str) -> str:
    (reason,) = [r for r in REMOVAL_REASONS if r.startswith(prefix)]
    return reason


def test_mapping_by_hand() -> None:
    frame, _ = convert_volve(synthetic_raw())
    assert len(frame) == 2
    # Sorted by time: the 25-hour October day comes first.
    b, a = frame.iloc[0], frame.iloc[1]

    assert a[schema.TIME] == pd.Timestamp("2015-03-05T12:00:00Z")
    assert a[schema.WELL] == "X-A"
    assert a["choke"] == pytest.approx(0.5)
    assert a["p_up"] == pytest.approx(40.0 + ATM)
    assert a["p_down"] == pytest.approx(30.0 + ATM)
    assert a["t_up"] == pytest.approx(70.0)
    assert a["q_oil"] == pytest.approx(10.0)  # 240 Sm3 / 24 h
    assert a["q_gas"] == pytest.approx(0.0)
    assert a["q_water"] == pytest.approx(20.0)  # 480 Sm3 / 24 h
    assert a[schema.TARGET] == pytest.approx(30.0)
    # No gas: oil 240 * 840 = 201,600 kg, water 480 * 1017.5 = 488,400 kg.
    assert a["eta_gas"] == pytest.approx(0.0)
    assert a["eta_oil"] == pytest.approx(201_600.0 / (201_600.0 + 488_400.0))
    assert a[schema.SOURCE] == "mpfm"

    assert b[schema.TIME] == pd.Timestamp("2014-10-26T12:00:00Z")
    assert b["choke"] == pytest.approx(1.0)  # fully open is kept, not clipped or dropped
    assert b["p_up"] == pytest.approx(30.0 + ATM)
    assert b["p_down"] == pytest.approx(28.0 + ATM)
    assert b["q_oil"] == pytest.approx(4.0)  # 100 Sm3 / 25 h on the day the clocks go back
    assert b["q_gas"] == pytest.approx(600.0)  # 15,000 Sm3 / 25 h
    assert b["q_water"] == pytest.approx(0.0)
    assert b[schema.TARGET] == pytest.approx(604.0)
    # Standard gas density p M / (R T) at 101325 Pa, 288.15 K, M = 0.0205 kg/mol.
    rho_gas = 101_325.0 * 0.0205 / (8.314462618 * 288.15)
    assert rho_gas == pytest.approx(0.867, abs=1e-3)
    mass_oil, mass_gas = 100.0 * 840.0, 15_000.0 * rho_gas
    assert b["eta_gas"] == pytest.approx(mass_gas / (mass_oil + mass_gas))
    assert b["eta_oil"] == pytest.approx(mass_oil / (mass_oil + mass_gas))


def test_constants() -> None:
    # the project's prior means, so that the phase split at prior densities inverts the import
    assert RHO_OIL == 840.0
    assert RHO_WAT == 1017.5
    assert RHO_GAS_SC == pytest.approx(101_325.0 * 0.0205 / (8.314462618 * 288.15))
    assert MIN_ON_STREAM_HOURS == 23.9


def test_every_removal_counted_under_its_reason() -> None:
    raw = synthetic_raw()
    frame, removed = convert_volve(raw)
    assert list(removed) == list(REMOVAL_REASONS)
    expected = dict.fromkeys(REMOVAL_REASONS, 0)
    for _, prefix in CASES:
        if prefix is not None:
            expected[reason_named(prefix)] += 1
    assert removed == expected
    low_dp = reason_named("choke pressure drop below")
    assert all(n > 0 for r, n in removed.items() if r != low_dp), "every reason has a case"
    assert removed[low_dp] == 0  # kept unless asked for
    assert len(frame) + sum(removed.values()) == len(raw)


def test_days_without_a_restricting_choke_are_removed_when_asked() -> None:
    raw = synthetic_raw()
    # X-A has 10 bar across its choke, X-B 2 bar: a 5-bar minimum removes X-B's day only
    frame, removed = convert_volve(raw, min_choke_dp_bar=5.0)
    assert frame[schema.WELL].tolist() == ["X-A"]
    assert removed[reason_named("choke pressure drop below")] == 1
    assert len(frame) + sum(removed.values()) == len(raw)
    with pytest.raises(DataError, match="--min-choke-dp 1"):
        convert_volve(raw, min_choke_dp_bar=-1.0)


def test_field_notes_find_allocation_and_an_open_choke() -> None:
    days = pd.date_range("2015-01-01 12:00", periods=40, freq="D", tz="UTC")
    rows = []
    for k, t in enumerate(days):
        gor = 150.0 + k % 5  # the field's GOR of the day, the same for both wells
        for well, oil, choke, dp in (("A", 20.0, 0.5, 10.0), ("B", 30.0, 1.0, 0.4)):
            rows.append(
                {
                    "time": t,
                    "well": well,
                    "choke": choke,
                    "p_up": 30.0,
                    "p_down": 30.0 - dp,
                    "q_oil": oil,
                    "q_gas": oil * gor,
                    "q_water": 10.0,
                    "q_total": oil * (1 + gor) + 10.0,
                }
            )
    notes = field_notes(pd.DataFrame(rows))
    assert notes[0].startswith("On 100 % of the well-days") and "allocated" in notes[0]
    assert notes[1].startswith("Gas is 99 % of q_total")
    (open_choke,) = [n for n in notes if n.startswith("B:")]
    assert (
        "fully open on 100 %" in open_choke and "less than 1 bar across it on 100 %" in open_choke
    )
    assert not [n for n in notes if n.startswith("A:")]


def test_duplicate_keeps_the_first() -> None:
    frame, _ = convert_volve(synthetic_raw())
    first = frame[frame[schema.WELL] == "X-A"]
    assert first["q_oil"].tolist() == pytest.approx([10.0])


def test_input_not_mutated() -> None:
    raw = synthetic_raw()
    before = raw.copy()
    convert_volve(raw)
    pd.testing.assert_frame_equal(raw, before)


def test_output_has_the_observation_columns() -> None:
    frame, _ = convert_volve(synthetic_raw())
    for column in (*schema.REQUIRED_COLUMNS, *schema.OPTIONAL_RATE_COLUMNS):
        assert column in frame.columns
    rates = frame["q_gas"] + frame["q_oil"] + frame["q_water"]
    np.testing.assert_allclose(frame[schema.TARGET], rates)


def test_missing_needed_column_names_it() -> None:
    raw = synthetic_raw().drop(columns=["DP_CHOKE_SIZE"])
    with pytest.raises(DataError, match="DP_CHOKE_SIZE"):
        convert_volve(raw)


def write_csv(path: Path, rows: list[str], header: list[str] = HEADER) -> Path:
    path.write_text("\n".join([",".join(header), *rows]) + "\n", encoding="utf-8")
    return path


def test_thousands_separators_and_empty_cells_parse(tmp_path: Path) -> None:
    row = (
        "22-Apr-15,NO X-A,1,X-A,2,TESTFIELD,3,RIG,24.00,,,,,43.5,%,50.125,60.5,20.000,"
        '"1,234","123,456","2,345",,production,OP'
    )
    raw = read_volve_csv(write_csv(tmp_path / "volve.csv", [row]))
    assert raw.loc[0, "BORE_OIL_VOL"] == 1234.0
    assert raw.loc[0, "BORE_GAS_VOL"] == 123_456.0
    assert raw.loc[0, "BORE_WAT_VOL"] == 2345.0
    assert raw.loc[0, "AVG_WHP_P"] == 50.125
    assert math.isnan(raw.loc[0, "AVG_DOWNHOLE_PRESSURE"])
    frame, _ = convert_volve(raw)
    assert frame.loc[0, "q_gas"] == pytest.approx(123_456.0 / 24.0)


def test_missing_file_names_it(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.csv"
    with pytest.raises(DataError, match="nowhere.csv"):
        read_volve_csv(path)


def test_missing_columns_in_file_named(tmp_path: Path) -> None:
    header = [c for c in HEADER if c not in ("AVG_WHT_P", "BORE_WAT_VOL")]
    path = write_csv(tmp_path / "short.csv", [",".join("1" for _ in header)], header)
    with pytest.raises(DataError, match="short.csv") as info:
        read_volve_csv(path)
    assert "AVG_WHT_P" in str(info.value) and "BORE_WAT_VOL" in str(info.value)


def test_text_in_number_column_names_column(tmp_path: Path) -> None:
    row = "22-Apr-15,NO X-A,1,X-A,2,F,3,RIG,24,,,,,43.5,%,fifty,60.5,20,1,2,3,,production,OP"
    path = write_csv(tmp_path / "bad.csv", [row])
    with pytest.raises(DataError, match="AVG_WHP_P.*fifty.*row 2"):
        read_volve_csv(path)


def test_needed_columns_are_in_the_volve_header() -> None:
    assert set(NEEDED_COLUMNS) <= set(HEADER)


def test_import_writes_and_reports(tmp_path: Path) -> None:
    src = tmp_path / "volve.csv"
    synthetic_raw().to_csv(src, index=False)
    report = import_volve(src, tmp_path / "obs.csv")
    assert report.n_read == len(CASES)
    assert report.n_written == 2
    assert report.n_written + sum(report.removed.values()) == report.n_read
    assert report.wells == {"X-A": 1, "X-B": 1}
    assert report.out == tmp_path / "obs.csv"
    back = load_observations(report.out)
    assert back.removed == {}
    assert len(back.frame) == 2
    pd.testing.assert_series_equal(back.frame["q_total"], frame_q_total(), check_names=False)
    text = report.summary()
    assert "wrote 2 observations" in text and "X-B" in text and "not a producer" in text


# The real, licensed file: read in place, never copied.


@pytest.fixture(scope="module")
def volve_raw() -> pd.DataFrame:
    if not VOLVE_CSV.is_file():
        pytest.skip(
            f"Volve data not found at {VOLVE_CSV}: it is licensed and lives beside the repo "
            "in ../shared/data/volve/"
        )
    return read_volve_csv(VOLVE_CSV)


def test_real_file_counts_and_sanity(volve_raw: pd.DataFrame) -> None:
    frame, removed = convert_volve(volve_raw)
    assert 6_000 <= len(frame) <= 8_000
    assert len(frame) + sum(removed.values()) == len(volve_raw)
    wells = frame[schema.WELL].value_counts()
    assert 5 <= len(wells) <= 6
    for well in ("15/9-F-1 C", "15/9-F-11", "15/9-F-12", "15/9-F-14", "15/9-F-15 D"):
        assert wells[well] > 100
    assert "15/9-F-4" not in wells  # the water injector
    assert frame["choke"].between(0.0, 1.0).all()
    assert (frame["p_down"] > 0).all()
    assert (frame["p_down"] < frame["p_up"]).all()
    assert frame["eta_gas"].between(0.0, 1.0).all()
    assert frame["eta_oil"].between(0.0, 1.0).all()
    assert (frame["eta_gas"] + frame["eta_oil"] <= 1.0 + 1e-12).all()
    assert (frame[schema.TARGET] > 0).all()
    assert not frame.duplicated([schema.TIME, schema.WELL]).any()


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_real_file_round_trip(volve_raw: pd.DataFrame, tmp_path: Path, suffix: str) -> None:
    report = import_volve(VOLVE_CSV, tmp_path / f"volve_obs{suffix}")
    assert report.n_read == len(volve_raw)
    back = load_observations(report.out)
    assert back.removed == {}, "every converted row passes the observation checks"
    assert len(back.frame) == report.n_written == sum(report.wells.values())
    assert back.frame[schema.WELL].value_counts().to_dict() == report.wells
    frame, _ = convert_volve(volve_raw)
    for column in ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil", "q_total"):
        np.testing.assert_allclose(back.frame[column], frame[column], rtol=1e-12)
