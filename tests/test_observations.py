"""Tests of the observation loader/writer: hard errors, filtered rows, types, order, round trips."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vfm_core.errors import DataError, ObservationFormatError
from vfm_core.observations import (
    LoadResult,
    load_observations,
    save_observations,
    validate_frame,
)
from vfm_core.schema import INPUT_COLUMNS, REQUIRED_COLUMNS

START = pd.Timestamp("2019-03-01T06:00:00Z")


def make_frame(n: int = 4, **columns: object) -> pd.DataFrame:
    """A valid observation frame of ``n`` rows, one hour apart, on wells A and B.

    Rows alternate between a measured (mpfm) and an unmeasured sample. Keyword arguments
    replace or add whole columns.
    """
    measured = np.arange(n) % 2 == 0
    frame = pd.DataFrame(
        {
            "time": pd.date_range(START, periods=n, freq="h"),
            "well": ["A" if i % 2 == 0 else "B" for i in range(n)],
            "choke": np.linspace(0.2, 0.8, n),
            "p_up": np.full(n, 120.0),
            "p_down": np.full(n, 40.0),
            "t_up": np.full(n, 75.0),
            "eta_gas": np.full(n, 0.1),
            "eta_oil": np.full(n, 0.6),
            "q_total": np.where(measured, 95.5, np.nan),
            "source": np.where(measured, "mpfm", ""),
        }
    )
    for name, values in columns.items():
        frame[name] = values
    return frame


def write_csv(tmp_path: Path, text: str, name: str = "obs.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


HEADER = "time,well,choke,p_up,p_down,t_up,eta_gas,eta_oil,q_total,source\n"
GOOD_LINE = "2019-03-01T06:00:00Z,A,0.5,120,40,75,0.1,0.6,95.5,mpfm\n"


def line(**cells: str) -> str:
    """One CSV data line: GOOD_LINE with some cells replaced."""
    values = dict(zip(HEADER.strip().split(","), GOOD_LINE.strip().split(","), strict=True))
    values.update(cells)
    return ",".join(values.values()) + "\n"


# --- a clean file ------------------------------------------------------------------------


def test_clean_frame_is_typed_and_nothing_removed() -> None:
    result = validate_frame(make_frame(4), name="clean")
    frame = result.frame
    assert isinstance(result, LoadResult)
    assert (result.path, result.n_read, result.removed, result.reordered) == ("clean", 4, {}, False)
    assert str(frame["time"].dtype) == "datetime64[ns, UTC]"
    for column in (*INPUT_COLUMNS, "q_total"):
        assert frame[column].dtype == np.float64, column
    assert frame["well"].tolist() == ["A", "B", "A", "B"]
    assert frame["source"].tolist() == ["mpfm", "", "mpfm", ""]
    assert np.isnan(frame["q_total"].iloc[1])
    assert frame.index.tolist() == [0, 1, 2, 3]


def test_csv_with_empty_cells_loads(tmp_path: Path) -> None:
    path = write_csv(
        tmp_path, HEADER + GOOD_LINE + line(time="2019-03-01T07:00:00Z", q_total="", source="")
    )
    result = load_observations(path)
    assert result.n_read == 2
    assert result.frame["source"].tolist() == ["mpfm", ""]
    assert result.frame["q_total"].iloc[0] == 95.5
    assert np.isnan(result.frame["q_total"].iloc[1])


def test_na_words_in_numeric_columns_mean_empty_but_well_ids_are_literal(tmp_path: Path) -> None:
    path = write_csv(tmp_path, HEADER + line(well="NA", q_total="NaN", source=""))
    frame = load_observations(path).frame
    assert frame["well"].tolist() == ["NA"]
    assert np.isnan(frame["q_total"].iloc[0])


def test_input_frame_is_not_changed() -> None:
    frame = make_frame(3).iloc[::-1]
    before = frame.copy()
    validate_frame(frame)
    pd.testing.assert_frame_equal(frame, before)


# --- hard errors -------------------------------------------------------------------------


def test_missing_required_columns_are_all_named(tmp_path: Path) -> None:
    path = tmp_path / "obs.csv"
    make_frame(2).drop(columns=["q_total", "source"]).to_csv(path, index=False)
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(f"file {path}: missing required column(s) 'q_total', 'source'.")
    assert ", ".join(REQUIRED_COLUMNS) in message
    assert info.value.path == str(path)


def test_text_in_numeric_column_names_row_column_value_and_count(tmp_path: Path) -> None:
    text = HEADER + GOOD_LINE + line(p_up="12O.5") + GOOD_LINE + line(p_up="high")
    path = write_csv(tmp_path, text)
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(f"file {path}, row 3, column 'p_up': '12O.5' is not a number")
    assert "1 other row has text in this column too" in message
    assert (info.value.row, info.value.column) == (3, "p_up")


def test_text_in_optional_rate_column_is_an_error() -> None:
    frame = make_frame(3, q_oil=["1.0", "2.0", "lots"])
    with pytest.raises(ObservationFormatError) as info:
        validate_frame(frame, name="mem")
    assert str(info.value).startswith("file mem, row 4, column 'q_oil': 'lots' is not a number")


def test_unparseable_time_names_row_and_value(tmp_path: Path) -> None:
    text = HEADER + GOOD_LINE + GOOD_LINE + line(time="01/03/2019 06:00") + line(time="")
    path = write_csv(tmp_path, text)
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(
        f"file {path}, row 4, column 'time': '01/03/2019 06:00' is not an ISO 8601 time"
    )
    assert "1 other row has an empty or unreadable time too" in message


def test_empty_time_is_an_error(tmp_path: Path) -> None:
    path = write_csv(tmp_path, HEADER + line(time=""))
    with pytest.raises(ObservationFormatError, match=r"row 2, column 'time': the time is empty"):
        load_observations(path)


def test_empty_well_id_is_an_error(tmp_path: Path) -> None:
    path = write_csv(tmp_path, HEADER + GOOD_LINE + line(well="  ") + line(well=""))
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(f"file {path}, row 3, column 'well': the well id is empty")
    assert "1 other row has an empty well id too" in message


def test_unknown_source_names_value_and_valid_ones(tmp_path: Path) -> None:
    path = write_csv(tmp_path, HEADER + GOOD_LINE + line(source="MPFM-2"))
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(
        f"file {path}, row 3, column 'source': 'MPFM-2' is not a valid source"
    )
    assert "'mpfm' or 'well_test'" in message
    assert "other row" not in message


def test_parquet_rows_are_numbered_like_csv(tmp_path: Path) -> None:
    frame = make_frame(4)
    frame["t_up"] = ["75", "75", "75", "warm"]
    path = tmp_path / "obs.parquet"
    frame.to_parquet(path, index=False)
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    assert str(info.value).startswith(f"file {path}, row 5, column 't_up': 'warm' is not a number")


def test_hard_errors_raise_even_without_filtering() -> None:
    frame = make_frame(2, source=["mpfm", "guess"])
    with pytest.raises(ObservationFormatError, match="'guess' is not a valid source"):
        validate_frame(frame, filter_illogical=False)


def test_unknown_suffix_is_rejected_with_accepted_ones(tmp_path: Path) -> None:
    path = tmp_path / "obs.xlsx"
    path.write_text("whatever")
    with pytest.raises(ObservationFormatError) as info:
        load_observations(path)
    message = str(info.value)
    assert message.startswith(f"file {path}: unknown file type")
    for suffix in (".csv", ".csv.gz", ".parquet", ".pq"):
        assert suffix in message
    with pytest.raises(ObservationFormatError, match="unknown file type"):
        save_observations(make_frame(2), tmp_path / "out.json")
    assert not (tmp_path / "out.json").exists()


def test_missing_file_is_a_data_error(tmp_path: Path) -> None:
    path = tmp_path / "nowhere.csv"
    with pytest.raises(DataError, match=r"does not exist") as info:
        load_observations(path)
    assert str(path) in str(info.value)
    assert not isinstance(info.value, ObservationFormatError)


def test_empty_csv_file_is_a_format_error(tmp_path: Path) -> None:
    path = write_csv(tmp_path, "")
    with pytest.raises(ObservationFormatError, match="the file is empty"):
        load_observations(path)


# --- filtered rows -----------------------------------------------------------------------

# Each case spoils row 1 (file row 3) of a valid 4-row frame in one way.
FILTER_CASES = {
    "non-finite input": {"t_up": np.inf},
    "negative or zero pressure": {"p_down": 0.0},
    "p_down >= p_up": {"p_down": 120.0},
    "choke outside 0..1": {"choke": 1.2},
    "fraction outside 0..1": {"eta_oil": -0.1},
    "fractions sum above 1": {"eta_gas": 0.5, "eta_oil": 0.6},
    "negative rate": {"q_total": -1.0, "source": "mpfm"},
    "rate without source": {"q_total": 80.0},
    "source without rate": {"source": "well_test"},
}


@pytest.mark.parametrize("reason", list(FILTER_CASES))
def test_each_illogical_row_is_removed_counted_and_logged(
    reason: str, caplog: pytest.LogCaptureFixture
) -> None:
    frame = make_frame(4)
    for column, value in FILTER_CASES[reason].items():
        frame.loc[1, column] = value
    with caplog.at_level(logging.WARNING, logger="vfm.observations"):
        result = validate_frame(frame, name="f.csv")
    assert result.removed == {reason: 1}
    assert result.n_read == 4
    assert len(result.frame) == 3
    assert START + pd.Timedelta(hours=1) not in set(result.frame["time"])
    assert [r.getMessage() for r in caplog.records] == [
        f"f.csv: removed 1 row: {reason} (first at row 3)."
    ]


def test_zero_upstream_pressure_is_counted_before_pressure_order() -> None:
    frame = make_frame(3)
    frame.loc[2, "p_up"] = 0.0  # also p_down >= p_up, which comes later in the order
    assert validate_frame(frame).removed == {"negative or zero pressure": 1}


#: inputs outside their physical span (vfm_core.sensor_faults.DEFAULT_RANGES): kept with
#: ``keep_out_of_range`` (vfm evaluate), removed otherwise under the reason given
OUT_OF_SPAN = {
    "p_down": (-1.0, "negative or zero pressure"),
    "p_up": (-1.0, "negative or zero pressure"),
    "choke": (1.2, "choke outside 0..1"),
    "eta_gas": (-0.1, "fraction outside 0..1"),
}


@pytest.mark.parametrize("column", list(OUT_OF_SPAN))
def test_an_input_out_of_its_span_is_kept_raw_for_the_detectors_when_asked(
    column: str, caplog: pytest.LogCaptureFixture
) -> None:
    """``keep_out_of_range``: a row whose only problem is an input outside its physical span
    is kept with its raw value and counted (an out_of_range fault for the detectors, not a
    lost row); without it the row is removed as before. A p_up of -1 is also below p_down:
    that check does not see the input set aside."""
    value, reason = OUT_OF_SPAN[column]
    frame = make_frame(4)
    frame.loc[1, column] = value
    assert validate_frame(frame).removed == {reason: 1}
    with caplog.at_level(logging.WARNING, logger="vfm.observations"):
        result = validate_frame(frame, name="f.csv", keep_out_of_range=True)
    assert result.removed == {}
    assert result.kept == {"input out of range": 1}
    assert len(result.frame) == 4
    assert result.frame.loc[1, column] == value  # the raw value, not a stand-in
    assert "kept 1 row with an input outside its physical span" in caplog.text
    assert "input out of range: 1 row kept" in result.summary()


def test_a_row_out_of_span_with_another_problem_is_still_removed() -> None:
    """Kept are only rows whose other checks pass: a negative p_down with a fraction sum
    above 1 is removed (under the first reason), and so is a zero pressure, which lies
    inside the detectors' span (0..1500 bar a) and would reach the model as read."""
    frame = make_frame(6)
    frame.loc[1, ["p_down", "eta_gas", "eta_oil"]] = [-1.0, 0.5, 0.6]
    frame.loc[3, "p_down"] = 0.0
    frame.loc[5, "choke"] = -0.5  # kept
    result = validate_frame(frame, keep_out_of_range=True)
    assert result.removed == {"negative or zero pressure": 1, "fractions sum above 1": 1}
    assert result.kept == {"input out of range": 1}
    assert result.frame["choke"].min() == -0.5


def test_duplicate_rows_are_removed_keeping_the_first() -> None:
    frame = make_frame(3)
    duplicate = frame.iloc[[0, 0]].assign(choke=[0.9, 0.7])
    result = validate_frame(pd.concat([frame, duplicate], ignore_index=True))
    assert result.removed == {"duplicate row": 2}
    assert result.frame["choke"].tolist() == pytest.approx([0.2, 0.5, 0.8])


def test_same_time_and_well_with_other_source_is_not_a_duplicate() -> None:
    frame = make_frame(1)
    other = frame.assign(source="well_test", q_total=90.0)
    result = validate_frame(pd.concat([frame, other], ignore_index=True))
    assert result.removed == {}
    assert result.frame["source"].tolist() == ["mpfm", "well_test"]


def test_infinite_q_total_counts_as_negative_rate() -> None:
    frame = make_frame(2)
    frame.loc[0, "q_total"] = np.inf
    assert validate_frame(frame).removed == {"negative rate": 1}


def test_negative_optional_rate_counts_as_negative_rate() -> None:
    frame = make_frame(3, q_water=[1.0, np.nan, -2.0])
    assert validate_frame(frame).removed == {"negative rate": 1}


def test_row_with_several_problems_counts_under_the_first_reason(
    caplog: pytest.LogCaptureFixture,
) -> None:
    frame = make_frame(6)
    # p_down >= p_up and choke > 1 and no source: counted as "p_down >= p_up".
    frame.loc[0, ["p_down", "choke", "source"]] = [130.0, 1.5, ""]
    # NaN input and negative pressure: counted as "non-finite input".
    frame.loc[1, ["choke", "p_up"]] = [np.nan, -3.0]
    # eta sum > 1 and a rate without a source: counted as "fractions sum above 1".
    frame.loc[3, ["eta_gas", "eta_oil", "q_total"]] = [0.7, 0.7, 50.0]
    # A duplicate of row 0, which is itself removed: the duplicate is kept.
    frame.loc[2, ["time", "well"]] = [frame.loc[0, "time"], "A"]
    with caplog.at_level(logging.WARNING, logger="vfm.observations"):
        result = validate_frame(frame)
    assert result.removed == {
        "non-finite input": 1,
        "p_down >= p_up": 1,
        "fractions sum above 1": 1,
    }
    assert list(result.removed) == ["non-finite input", "p_down >= p_up", "fractions sum above 1"]
    assert len(result.frame) == 3
    assert len(caplog.records) == 3


def test_filter_can_be_switched_off() -> None:
    frame = make_frame(4)
    frame.loc[0, "p_down"] = 500.0
    frame.loc[1, "source"] = "mpfm"
    frame = pd.concat([frame, frame.iloc[[2]]], ignore_index=True)
    result = validate_frame(frame, filter_illogical=False)
    assert result.removed == {}
    assert len(result.frame) == 5


def test_summary_names_counts_and_reordering() -> None:
    frame = make_frame(3)
    frame.loc[1, "p_down"] = 200.0
    result = validate_frame(frame.iloc[::-1], name="field.csv")
    assert result.summary() == (
        "field.csv: 3 rows read, 2 kept; removed 1 (p_down >= p_up: 1); "
        "rows were re-sorted into time order."
    )
    assert validate_frame(make_frame(1), name="one.csv").summary() == "one.csv: 1 row read, 1 kept."


# --- order, columns, times ---------------------------------------------------------------


def test_unsorted_rows_are_sorted_by_time_then_well() -> None:
    frame = make_frame(4)
    frame["time"] = pd.to_datetime(
        ["2019-03-02T00:00Z", "2019-03-01T00:00Z", "2019-03-01T00:00Z", "2019-03-01T12:00Z"]
    )
    frame["well"] = ["A", "C", "B", "A"]
    frame.index = [10, 11, 12, 13]
    result = validate_frame(frame)
    assert result.reordered is True
    assert result.frame["well"].tolist() == ["B", "C", "A", "A"]
    assert result.frame["time"].tolist() == list(
        pd.to_datetime(
            ["2019-03-01T00:00Z", "2019-03-01T00:00Z", "2019-03-01T12:00Z", "2019-03-02T00:00Z"]
        )
    )
    assert result.frame.index.tolist() == [0, 1, 2, 3]


def test_sort_is_stable_for_equal_time_and_well() -> None:
    frame = make_frame(3, time=[START] * 3, well=["A"] * 3, source=["mpfm", "", "well_test"])
    frame["q_total"] = [1.0, np.nan, 2.0]
    result = validate_frame(frame)
    assert result.reordered is False
    assert result.frame["source"].tolist() == ["mpfm", "", "well_test"]


def test_extra_columns_are_kept_unchanged(tmp_path: Path) -> None:
    frame = make_frame(3, comment=["ok", "check", "ok"], sensor_id=[7, 8, 9])
    path = save_observations(frame, tmp_path / "obs.csv")
    loaded = load_observations(path).frame
    assert loaded["comment"].tolist() == ["ok", "check", "ok"]
    assert loaded["sensor_id"].tolist() == [7, 8, 9]
    assert loaded["sensor_id"].dtype == np.int64
    assert list(loaded.columns) == list(frame.columns)


def test_optional_rate_columns_are_parsed(tmp_path: Path) -> None:
    text = HEADER.strip() + ",q_gas,q_oil,q_water\n" + GOOD_LINE.strip() + ",60.5,30,\n"
    frame = load_observations(write_csv(tmp_path, text)).frame
    for column in ("q_gas", "q_oil", "q_water"):
        assert frame[column].dtype == np.float64, column
    assert frame[["q_gas", "q_oil"]].iloc[0].tolist() == [60.5, 30.0]
    assert np.isnan(frame["q_water"].iloc[0])


def test_naive_and_offset_times_are_the_same_utc_instant(tmp_path: Path) -> None:
    text = (
        HEADER
        + line(time="2019-03-01T06:00:00", well="naive")
        + line(time="2019-03-01T07:00:00+01:00", well="offset")
        + line(time="2019-03-01T06:00:00Z", well="zulu")
        + line(time="2019-03-01T01:00:00-05:00", well="west")
    )
    frame = load_observations(write_csv(tmp_path, text)).frame
    assert set(frame["time"]) == {pd.Timestamp("2019-03-01T06:00:00", tz="UTC")}
    assert str(frame["time"].dtype) == "datetime64[ns, UTC]"


def test_naive_and_aware_datetime_columns_in_memory() -> None:
    naive = make_frame(2, time=pd.to_datetime(["2019-03-01 06:00", "2019-03-01 07:00"]))
    oslo = make_frame(2)
    oslo["time"] = naive["time"].dt.tz_localize("UTC").dt.tz_convert("Europe/Oslo")
    pd.testing.assert_series_equal(
        validate_frame(naive).frame["time"], validate_frame(oslo).frame["time"]
    )
    assert validate_frame(naive).frame["time"].iloc[0] == pd.Timestamp("2019-03-01T06:00Z")


# --- writing -----------------------------------------------------------------------------


def round_trip_frame() -> pd.DataFrame:
    frame = make_frame(
        6,
        q_gas=[60.1, np.nan, 1 / 3, np.nan, 2e-7, np.nan],
        note=["a", "b", "c", "d", "e", "f"],
    )
    frame["choke"] = np.random.default_rng(3).random(6)
    frame.loc[5, "time"] = frame.loc[5, "time"] + pd.Timedelta(microseconds=250)
    return validate_frame(frame).frame


@pytest.mark.parametrize("name", ["obs.csv", "obs.csv.gz", "obs.parquet", "obs.pq"])
def test_round_trip(tmp_path: Path, name: str) -> None:
    frame = round_trip_frame()
    path = save_observations(frame, tmp_path / "nested" / "dir" / name)
    assert path == tmp_path / "nested" / "dir" / name
    loaded = load_observations(path)
    assert loaded.removed == {}
    assert loaded.reordered is False
    pd.testing.assert_frame_equal(loaded.frame, frame)
    assert sorted(os.listdir(path.parent)) == [name]  # no temporary file left behind


def test_csv_times_are_iso_utc_and_empty_cells_empty(tmp_path: Path) -> None:
    frame = make_frame(2)
    frame["time"] = pd.to_datetime(["2019-03-01T07:00:00+01:00", "2019-03-01T08:00:00+01:00"])
    path = save_observations(frame, tmp_path / "obs.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == HEADER.strip()
    assert lines[1] == "2019-03-01T06:00:00Z,A,0.2,120.0,40.0,75.0,0.1,0.6,95.5,mpfm"
    assert lines[2] == "2019-03-01T07:00:00Z,B,0.8,120.0,40.0,75.0,0.1,0.6,,"


def test_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = save_observations(make_frame(2), tmp_path / "obs.parquet")
    before = path.read_bytes()

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        save_observations(make_frame(5), path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["obs.parquet"]


def test_save_refuses_a_frame_that_breaks_the_format(tmp_path: Path) -> None:
    with pytest.raises(ObservationFormatError, match="column 'well': the well id is empty"):
        save_observations(make_frame(2, well=["A", ""]), tmp_path / "obs.csv")
    assert not (tmp_path / "obs.csv").exists()


# --- size --------------------------------------------------------------------------------


def test_thirty_thousand_rows_validate() -> None:
    n = 30_000
    rng = np.random.default_rng(0)
    frame = make_frame(n)
    frame["time"] = frame["time"].astype(str)  # as text, the way a CSV is read
    frame["choke"] = rng.uniform(0.0, 1.0, n).astype(str)
    frame.loc[n - 1, "p_down"] = 999.0
    result = validate_frame(frame)
    assert result.n_read == n
    assert result.removed == {"p_down >= p_up": 1}
    assert len(result.frame) == n - 1
    assert result.frame["choke"].dtype == np.float64
