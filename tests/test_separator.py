"""Separator readings: the format's refusals, the joint update by hand, learning and allocation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.errors import ConfigError, ObservationFormatError
from vfm_core.observations import load_observations, save_observations, validate_frame
from vfm_core.separator import run_separator, sum_update
from vfm_core.separator_format import member_samples
from vfm_core.separator_sim import simulate_separator_field

T0 = pd.Timestamp("2020-01-01T06:00:00Z")


def _well_row(well: str, hours: float = 0.0, choke: float = 0.5, sep: str = "S1") -> dict:
    return {
        "time": T0 + pd.Timedelta(hours=hours),
        "well": well,
        "choke": choke,
        "p_up": 100.0,
        "p_down": 30.0,
        "t_up": 60.0,
        "eta_gas": 0.1,
        "eta_oil": 0.8,
        "q_total": np.nan,
        "source": "",
        "separator": sep,
    }


def _reading(total: float, hours: float = 0.0, name: str = "S1", **inputs: float) -> dict:
    row = {c: np.nan for c in ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")}
    row.update(inputs)
    return {
        "time": T0 + pd.Timedelta(hours=hours),
        "well": name,
        **row,
        "q_total": total,
        "source": "separator",
        "separator": "",
    }


def _frame(*rows: dict) -> pd.DataFrame:
    return pd.DataFrame(list(rows))


# --- the format ------------------------------------------------------------------------------


def test_separator_rows_are_split_off_and_written_back(tmp_path):
    frame = _frame(_well_row("A"), _well_row("B"), _reading(120.0))
    loaded = validate_frame(frame)
    assert list(loaded.frame["well"]) == ["A", "B"]
    assert loaded.separators.members == {"S1": ["A", "B"]}
    assert loaded.separators.readings["q_total"].tolist() == [120.0]
    path = save_observations(frame, tmp_path / "f.csv")
    again = load_observations(path)
    assert again.separators.readings["q_total"].tolist() == [120.0]
    assert len(again.frame) == 2


@pytest.mark.parametrize(
    ("bad", "words"),
    [
        (_reading(120.0, p_up=50.0), "Leave the input columns of a separator row empty"),
        (_reading(-5.0), "a finite number of at least 0"),
        (_reading(np.nan), "the separator's total is empty"),
        (_reading(120.0, name="S9"), "no well flows into the separator 'S9'"),
        (_reading(120.0, name="A"), "'A' is the name of a well as well as of a separator"),
    ],
)
def test_bad_separator_rows_are_refused_with_a_sentence(bad, words):
    with pytest.raises(ObservationFormatError, match=words) as info:
        validate_frame(_frame(_well_row("A"), _well_row("B"), bad), name="f.csv")
    assert "row 4" in str(info.value)  # header row 1, the reading is the third data row


def test_a_well_in_two_separators_and_a_disagreeing_configuration_are_refused():
    with pytest.raises(ObservationFormatError, match="flows into one separator"):
        validate_frame(_frame(_well_row("A"), _well_row("A", 1.0, sep="S2"), _reading(1.0)))
    rows = _frame(_well_row("A"), _well_row("B"), _reading(1.0))
    with pytest.raises(ObservationFormatError, match="make them agree"):
        validate_frame(rows, separators={"A": "S2"})


def test_the_configuration_can_map_wells_to_separators():
    rows = _frame(_well_row("A", sep=""), _well_row("B", sep=""), _reading(10.0, name="X"))
    with pytest.raises(ObservationFormatError, match="no well flows"):
        validate_frame(rows)
    loaded = validate_frame(rows, separators={"A": "X", "B": "X"})
    assert loaded.separators.members == {"X": ["A", "B"]}


def test_samples_at_other_instants_and_shut_in_wells():
    rows = _frame(
        _well_row("A", -2.0),  # 2 h before the reading: counts
        _well_row("B", -7.0),  # 7 h before: older than the 6 h window, shut in
        _well_row("C", 0.0, choke=0.0),  # closed: shut in
        _well_row("D", 1.0),  # after the reading: not yet
        _reading(10.0),
    )
    loaded = validate_frame(rows)
    got = member_samples(loaded.frame, loaded.separators.readings, loaded.separators.members)
    shut = dict(zip(got["well"], got["shut"], strict=True))
    assert shut == {"A": False, "B": True, "C": True, "D": True}


# --- the joint update by hand ------------------------------------------------------------------


def test_sum_update_by_hand():
    # x ~ N([1, 2], diag(1, 4)), z = x1 + x2 + e, R = 1, z = 6: S = 6, K = [1/6, 4/6]
    mean, cov, s = sum_update(
        torch.tensor([1.0, 2.0], dtype=torch.float64),
        torch.diag(torch.tensor([1.0, 4.0], dtype=torch.float64)),
        torch.tensor([1.0, 1.0], dtype=torch.float64),
        innovation=6.0 - 3.0,
        noise_var=1.0,
    )
    assert s == pytest.approx(6.0)
    assert mean.tolist() == pytest.approx([1.5, 4.0])
    expected = [[5 / 6, -2 / 3], [-2 / 3, 4 / 3]]
    assert cov.tolist() == [pytest.approx(r) for r in expected]


def test_sum_update_equals_the_information_form():
    rng = np.random.default_rng(3)
    a = rng.standard_normal((6, 6))
    cov = torch.tensor(a @ a.T + np.eye(6), dtype=torch.float64)
    g = torch.tensor(rng.standard_normal(6), dtype=torch.float64)
    mean = torch.tensor(rng.standard_normal(6), dtype=torch.float64)
    new_mean, new_cov, _ = sum_update(mean, cov, g, innovation=0.7, noise_var=0.3)
    info = torch.linalg.inv(cov) + torch.outer(g, g) / 0.3
    want_cov = torch.linalg.inv(info)
    want_mean = want_cov @ (torch.linalg.inv(cov) @ mean + g * (0.7 + float(g @ mean)) / 0.3)
    torch.testing.assert_close(new_cov, want_cov)
    torch.testing.assert_close(new_mean, want_mean)


# --- the simulator -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def field():
    return simulate_separator_field(wells=4, years=2.0, seed=5, hidden=["erosion:rate=0.1"])


def test_simulated_separator_total_is_the_sum_of_its_wells(field):
    obs, truth = field.observations, field.truth_samples
    is_sep = (obs["source"] == "separator").to_numpy()
    assert is_sep.sum() > 300
    wells = obs[~is_sep & (obs["source"] != "well_test")]
    assert wells["q_total"].isna().all()  # per-well rates hidden
    assert set(wells["separator"]) == {"SEP"}
    per_time = truth.loc[~is_sep & (obs["source"] != "well_test").to_numpy()]
    sums = per_time.groupby("time")["q_true"].sum()
    sep_truth = truth.loc[is_sep].set_index("time")["q_true"]
    np.testing.assert_allclose(sep_truth.to_numpy(), sums.loc[sep_truth.index].to_numpy())
    rel = obs.loc[is_sep, "q_total"].to_numpy() / sep_truth.to_numpy() - 1.0
    assert 0.01 < rel.std() < 0.02  # the stated 1.5 % noise


# --- learning and allocation ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def runs(field):
    torch.set_num_threads(1)
    loaded = validate_frame(field.observations)
    truth = field.truth_samples[["time", "well", "q_true"]]
    out = {}
    for learn in (False, True):
        run = run_separator(loaded.frame, loaded.separators, "mm", learn=learn)
        p = run.predictions.merge(truth, on=["time", "well"])
        err = ((p["predicted"] - p["q_true"]).abs() / p["q_true"]).groupby(p["well"]).mean()
        out[learn] = (run, err)
    return out


def test_learning_from_the_separator_lowers_each_wells_error(runs):
    (_, without), (run, with_sep) = runs[False], runs[True]
    assert run.counts["taken"] > 100
    assert with_sep.mean() < 0.8 * without.mean()
    assert (with_sep < without).sum() >= 3  # of 4 wells


def test_allocation_sums_to_the_measured_total(runs):
    run, _ = runs[True]
    a = run.allocation
    assert not a.empty
    per = a.groupby(["time", "separator"]).agg(
        alloc=("q_alloc", "sum"), pred=("q_pred", "sum"), residual=("residual", "first")
    )
    np.testing.assert_allclose(per["alloc"], per["pred"] + per["residual"], rtol=1e-9)
    flowing = a["q_pred"] > 0
    assert (a.loc[flowing, "lo90"] < a.loc[flowing, "q_alloc"]).all()
    assert (a.loc[flowing, "q_alloc"] < a.loc[flowing, "hi90"]).all()
    assert (a.loc[~flowing, "q_alloc"] == 0).all()


def test_ol_and_pbl_say_they_ignore_the_separator(field):
    loaded = validate_frame(field.observations)
    with pytest.raises(ConfigError, match="ignores separator readings"):
        run_separator(loaded.frame, loaded.separators, "mm", "pbl:30d")


def test_a_well_test_reaches_its_partners_as_the_full_joint_update_says(field):
    """With cross-covariances kept, a well test on one well moves its separator partners
    exactly as one Kalman step on the stacked state would (the linearised, Gaussian case)."""
    from vfm_core.data import make_batch
    from vfm_core.learning import DEFAULT_TRAIN, parse_method
    from vfm_core.models import make_model
    from vfm_core.separator import SeparatorLearner

    torch.set_num_threads(1)
    loaded = validate_frame(field.observations)
    frame, seps = loaded.frame, loaded.separators
    wells = seps.members["SEP"]
    is_test = (frame["source"] == "well_test").to_numpy()
    split = pd.Timestamp("2017-06-01", tz="UTC")
    model = make_model("mm", wells, seed=0)
    meth = parse_method("bayes")
    meth.bind(model, train=DEFAULT_TRAIN["mm"])
    meth.fit(make_batch(frame, wells, rows=np.flatnonzero(is_test & (frame["time"] < split))))
    learner = SeparatorLearner(meth, seps.members, cross=True)
    # a reading at which every well has its sample, then the next well test
    readings = seps.readings[seps.readings["time"] >= split]
    complete = [
        k
        for k, t in enumerate(readings["time"])
        if ((frame["time"] == t).to_numpy() & ~is_test).sum() == len(wells)
    ]
    when, measured = readings["time"].iat[complete[0]], float(readings["q_total"].iat[complete[0]])
    rows = np.flatnonzero((frame["time"] == when).to_numpy() & ~is_test)
    one = make_batch(frame, wells, rows=rows)
    assert learner.allocate_and_learn("SEP", one, one.mask[:, 0], float(measured), when).learned
    test_row = int(np.flatnonzero(is_test & (frame["time"] > when).to_numpy())[0])
    test = make_batch(frame, wells, rows=[test_row])
    i = wells.index(str(frame["well"].iat[test_row]))
    d = meth.filter_state()[1].shape[-1]
    theta0, P_before, _, _ = meth.filter_state()
    grown = meth.grown_covariance(test.time_ns[:, 0].clamp(max=int(test.time_ns[i, 0])))
    joint = learner._joint["SEP"].clone()
    for k in range(len(wells)):
        joint[k * d : (k + 1) * d, k * d : (k + 1) * d] = grown[k]
    h = meth.log_rate_and_gradient(test, test.mask[:, 0])[1][i]

    learner.learn_well_tests(test)
    theta1, P_after, _, _ = meth.filter_state()
    # the well's own step gives its effective noise and innovation (a rank-one update)
    a = float(h @ grown[i] @ h)
    b = float(h @ P_after[i] @ h)
    assert b < a  # the test was taken
    noise_var = a * a / (a - b) - a
    innovation = float(h @ (theta1[i] - theta0[i])) * (a + noise_var) / a
    g = torch.zeros(len(wells) * d, dtype=torch.float64)
    g[i * d : (i + 1) * d] = h
    mean, cov, _ = sum_update(theta0.reshape(-1), joint, g, innovation, noise_var)
    partners = [k for k in range(len(wells)) if k != i]
    moved = max(float((theta1[k] - theta0[k]).abs().max()) for k in partners)
    assert moved > 1e-6  # the partners did move
    for k in partners:
        blk = slice(k * d, (k + 1) * d)
        torch.testing.assert_close(theta1[k], mean[blk], rtol=1e-6, atol=1e-9)
        shrink = (grown[k] - cov[blk, blk]).clone()
        torch.testing.assert_close(P_before[k] - P_after[k], shrink, rtol=1e-5, atol=1e-12)
        own = slice(i * d, (i + 1) * d)
        torch.testing.assert_close(
            learner._joint["SEP"][blk, own], cov[blk, own], rtol=1e-5, atol=1e-12
        )


def test_the_block_diagonal_path_equals_the_joint_one_on_a_first_reading(field):
    """Before any reading the wells are uncorrelated, so the O(M D^2) path (cross=False)
    must give the very update of the stacked one (cross=True)."""
    from vfm_core.data import make_batch
    from vfm_core.learning import DEFAULT_TRAIN, parse_method
    from vfm_core.models import make_model
    from vfm_core.separator import SeparatorLearner

    torch.set_num_threads(1)
    loaded = validate_frame(field.observations)
    frame, seps = loaded.frame, loaded.separators
    wells = seps.members["SEP"]
    is_test = (frame["source"] == "well_test").to_numpy()
    split = pd.Timestamp("2017-06-01", tz="UTC")
    readings = seps.readings[seps.readings["time"] >= split]
    when, measured = readings["time"].iat[0], float(readings["q_total"].iat[0]) * 1.05
    rows = np.flatnonzero((frame["time"] == when).to_numpy() & ~is_test)
    states = []
    for cross in (True, False):
        model = make_model("mm", wells, seed=0)
        meth = parse_method("bayes")
        meth.bind(model, train=DEFAULT_TRAIN["mm"])
        meth.fit(make_batch(frame, wells, rows=np.flatnonzero(is_test & (frame["time"] < split))))
        learner = SeparatorLearner(meth, seps.members, cross=cross)
        one = make_batch(frame, wells, rows=rows)
        theta_before = meth.filter_state()[0]
        alloc = learner.allocate_and_learn("SEP", one, one.mask[:, 0], measured, when)
        states.append((theta_before, meth.filter_state(), alloc))
    (before, joint, a_joint), (_, block, a_block) = states
    assert a_joint.learned and a_block.learned
    assert float((joint[0] - before).abs().max()) > 1e-6  # the reading moved the wells
    torch.testing.assert_close(joint[0], block[0])  # parameters
    torch.testing.assert_close(joint[1], block[1])  # covariances
    np.testing.assert_allclose(a_joint.q_alloc, a_block.q_alloc)


def test_without_learning_hams_run_refits_as_the_study_does(field):
    """``ham`` + ``bayes`` refits its wells every 14 days while they learn from well tests
    only (``refresh=auto``); without the readings the run is the study's case 2 run, refits
    included (before session 57 it never refitted: 1.38 % against the study's 1.34 % on
    an 8-well field), and with them the readings end the refits (they are continuous)."""
    from vfm_core.jobs.study import run_prequential

    loaded = validate_frame(field.observations)
    plain = run_prequential(loaded.frame, "ham", "bayes", targets="well_test").predictions
    base = run_separator(loaded.frame, loaded.separators, "ham", learn=False)
    both = base.predictions.merge(plain, on=["time", "well"])
    assert len(both) == len(plain) == len(base.predictions) > 10
    np.testing.assert_allclose(both["predicted_x"], both["predicted_y"], rtol=1e-9)


def test_without_learning_the_run_is_the_plain_case_2_filter(field, runs):
    """The baseline the benchmark compares with is the study's own bayes run of case 2."""
    from vfm_core.jobs.study import run_prequential

    loaded = validate_frame(field.observations)
    plain = run_prequential(loaded.frame, "mm", "bayes", targets="well_test").predictions
    base, _ = runs[False]
    both = base.predictions.merge(plain, on=["time", "well"])
    assert len(both) == len(plain) == len(base.predictions) > 10
    np.testing.assert_allclose(both["predicted_x"], both["predicted_y"], rtol=1e-12)


# --- vfm evaluate on a separator field ----------------------------------------------------------


def test_vfm_evaluate_writes_the_allocation_and_the_readings_gain(field, runs, tmp_path, capsys):
    """The user's path: ``vfm evaluate`` on a file with separator readings writes
    allocation.parquet (each reading's wells' rates summing to its total), gives each run's
    well-test MAPE with and without the readings in metrics.json (``separators``), the
    console and the report, and the "without" figure is the study's own bayes run of case 2
    on the same well tests (another code path: run_prequential)."""
    import json

    from vfm_core.cli import main

    data = save_observations(field.observations, tmp_path / "sep.parquet")
    out = tmp_path / "study"
    args = ["evaluate", str(data), "--out", str(out), "--models", "mm", "--methods", "bayes"]
    assert main([*args, "--targets", "well_test", "--quiet", "--jobs", "1"]) == 0
    printed = capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    (sep,) = metrics["separators"]
    assert (sep["model"], sep["method"]) == ("mm", "bayes")
    (study,) = [r for r in metrics["summary"] if r["method"] == "bayes" and "target" not in r]
    assert sep["well_test_mape_without_percent"] == pytest.approx(study["mean_mape"], rel=1e-9)
    # the same run as the module's own (the readings learned from): the same figures
    run, _ = runs[True]
    assert sep["readings_learned"] == run.counts["taken"] > 100
    assert sep["well_test_mape_percent"] == pytest.approx(run.well_mape().mean(), rel=1e-9)
    assert sep["well_test_mape_percent"] < sep["well_test_mape_without_percent"]
    assert sep["lower_percent"] == pytest.approx(
        100 * (1 - sep["well_test_mape_percent"] / sep["well_test_mape_without_percent"])
    )
    tests = (field.observations["source"] == "well_test") & (
        field.observations["time"] >= pd.Timestamp(metrics["split"])
    )
    assert sum(w["n"] for w in sep["wells"].values()) == int(tests.sum())
    assert f"well tests {sep['well_test_mape_percent']:.2f} % MAPE" in printed
    assert f"({sep['well_test_mape_without_percent']:.2f} % without the readings" in printed
    # the allocation: every reading after the split, its wells' rates summing to its total
    alloc = pd.read_parquet(out / "allocation.parquet")
    readings = field.observations[field.observations["source"] == "separator"]
    readings = readings[readings["time"] >= pd.Timestamp(metrics["split"])]
    per = alloc.groupby("time")["q_alloc"].sum()
    assert len(per) == len(readings) == sep["readings_learned"]
    np.testing.assert_allclose(
        per.to_numpy(), readings.set_index("time").loc[per.index, "q_total"].to_numpy(), rtol=1e-9
    )
    html = (out / "report.html").read_text()
    assert "<h2>Separator totals</h2>" in html
    assert "separator total against the sum of the wells&#39; predictions" in html or (
        "separator total against the sum of the wells' predictions" in html
    )
