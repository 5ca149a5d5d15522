"""``bayes`` on a shared model refits the network under its filter (the rule and its reason:
docs/guide/bayes.md, "A shared model's network: refitted under the filter").

The filter of ``mtl`` carries a posterior over each well's task vector only; the shared
layers are the same for every well, so only a joint fit on every well's measurements can
move them. Every 14 days the model is refitted (MAP, warm-started, as ``pbl`` retrains) and
the filter starts again from the refit.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import mape, run_prequential, wells_of
from vfm_core.learning import DEFAULT_TRAIN, bayes, parse_method
from vfm_core.learning.memory import FrameMemory
from vfm_core.models import make_model
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

T0 = 1_500_000_000_000_000_000  # epoch ns
DAY = 86_400_000_000_000  # ns


def _due_after_start(text: str, model_name: str) -> int | None:
    """The next refit of ``text`` bound to a fresh two-well ``model_name``, started at T0
    (ns after T0; None: no refit)."""
    method = parse_method(text).bind(make_model(model_name, ["A", "B"]))
    method.start(T0)
    due = method.next_due()
    return None if due is None else due - T0


def test_the_refit_is_on_for_shared_models_and_can_be_set() -> None:
    """``auto`` (the default) refits a shared model every 14 days, a per-well hybrid's
    wells as often once they learn from well tests only (none seen here: no refit; see
    the next test), no other; ``off`` and a span set it; a bad span says what is wrong;
    ``period`` (read by the service) says the same, also before binding."""
    assert _due_after_start("bayes", "mtl") == 14 * DAY
    for name in ("nn", "hem", "ham", "mm", "lr"):
        assert _due_after_start("bayes", name) is None, name
    assert _due_after_start("bayes:refresh=off", "mtl") is None
    assert _due_after_start("bayes:refresh=0", "mtl") is None
    assert _due_after_start("bayes:refresh=30d", "nn") == 30 * DAY
    assert parse_method("bayes:refresh=30d").period == pd.Timedelta(days=30)
    assert parse_method("bayes:refresh=off").period is None
    assert parse_method("bayes").bind(make_model("ham", ["A"])).period == pd.Timedelta(days=14)
    assert parse_method("bayes").bind(make_model("nn", ["A"])).period is None
    assert parse_method("bayes").bind(make_model("mm", ["A"])).period is None
    assert parse_method("bayes").bind(make_model("mtl", ["A"])).period == pd.Timedelta(days=14)
    with pytest.raises(ConfigError, match="refresh period 'soon' is not a positive time span"):
        parse_method("bayes:refresh=soon")


def test_missed_refits_each_run_and_the_calendar_survives_a_checkpoint(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A gap of 100 days (seven refits due) runs the seven refits, each on the
    measurements before its due time, as ``pbl`` retrains; the filter starts again once,
    after the last (its two Kalman passes over the history); the next refit falls 14 days
    later, also after a restore."""
    frame = validate_frame(simulate_field(wells=2, years=1.0, seed=23).observations).frame
    wells = wells_of(frame)
    memory = FrameMemory(frame, target_mask(frame, "all"), wells)
    t_split = int(pd.Timestamp("2016-07-01", tz="UTC").value)
    model = make_model("mtl", wells)
    method = parse_method("bayes").bind(
        model, train=replace(DEFAULT_TRAIN["mtl"], max_iter=60, early_stopping=False)
    )
    method.fit(memory.batch(t_split))
    method.start(t_split)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    assert not method.retrain_due(memory, torch.full((2,), t_split + DAY)).any()
    assert method.n_retrains == 0
    passes = []
    history_pass = bayes._history_pass

    def counted(*args: Any) -> Any:
        passes.append(1)
        return history_pass(*args)

    monkeypatch.setattr(bayes, "_history_pass", counted)
    changed = method.retrain_due(memory, torch.full((2,), t_split + 100 * DAY))
    assert changed.all() and method.n_retrains == 7
    assert method.retrains == [t_split + k * 14 * DAY for k in range(1, 8)]
    assert len(passes) == 2  # one start of the filter: two passes over the history
    assert method.next_due() == t_split + 112 * DAY
    # the shared layers moved (refitted on the 98 more days), not only the task vectors
    assert not torch.allclose(model.state_dict()["w_in"], before["w_in"])
    twin = parse_method("bayes").bind(make_model("mtl", wells))
    twin.load_state_dict(method.state_dict())
    assert twin.next_due() == t_split + 112 * DAY


def _one_row(memory: FrameMemory, well: int, t_ns: int) -> Any:
    """The measurement of well number ``well`` at ``t_ns`` from ``memory``, alone."""
    batch = memory.batch(t_ns + 1)
    keep = torch.zeros_like(batch.mask)
    keep[well] = batch.mask[well] & (batch.time_ns[well] == t_ns)
    assert int(keep.sum()) == 1
    return batch.select(keep)


def test_auto_refits_a_hybrid_well_that_learns_from_well_tests_only() -> None:
    """``auto`` on ``ham``: of two wells, the one without an MPFM (B: well tests only) is
    refitted every 14 days, its network's lower layer with it; the one with an MPFM (A) is
    not. An MPFM reading of B ends its refits; a well test of A after 30 days without an
    MPFM reading (its meter failed) starts them. The calendar survives a checkpoint, and a
    checkpoint from before (without the meters' times) still restores."""
    frame = validate_frame(simulate_field(wells=2, years=1.5, seed=23).observations).frame
    wells = wells_of(frame)
    is_b = (frame["well"] == wells[1]).to_numpy()
    mpfm = (frame["source"] == "mpfm").to_numpy()
    every = target_mask(frame, "all")
    memory = FrameMemory(frame, every & ~(is_b & mpfm), wells)
    t_split = int(pd.Timestamp("2016-07-01", tz="UTC").value)
    model = make_model("ham", wells)
    train = replace(DEFAULT_TRAIN["ham"], max_iter=60, early_stopping=False)
    method = parse_method("bayes").bind(model, train=train)
    method.fit(memory.batch(t_split))
    method.start(t_split)
    never = torch.iinfo(torch.int64).max
    assert method._refresh_at.tolist() == [never, t_split + 14 * DAY]
    assert method.next_due() == t_split + 14 * DAY
    lower = model.net.weights[0].detach().clone()
    a_meters = method._meter_t[0].copy()
    changed = method.retrain_due(memory, torch.full((2,), t_split + 100 * DAY))
    assert changed.tolist() == [False, True] and method.n_retrains == 7
    # B's refits read A's measurements up to their due time; A, not refitted, has not
    # learned them: its meters stay as they were (else, learning them later, it skipped
    # them, and a young well's refits never started: helper refresh57)
    assert np.array_equal(method._meter_t[0], a_meters), (method._meter_t[0], a_meters)
    moved = (model.net.weights[0].detach() - lower).abs().amax(dim=(1, 2))
    assert moved[0] == 0.0 and moved[1] > 1e-3, moved
    assert method.next_due() == t_split + 112 * DAY
    # a checkpoint keeps the calendar and the meters; one from before restores too
    state = method.state_dict()
    twin = parse_method("bayes").bind(make_model("ham", wells), train=train)
    twin.load_state_dict(state)
    assert torch.equal(twin._refresh_at, method._refresh_at)
    assert np.array_equal(twin._meter_t, method._meter_t) and twin.next_due() == method.next_due()
    old = {k: v for k, v in state.items() if k != "meter_t"}
    twin = parse_method("bayes").bind(make_model("ham", wells), train=train)
    twin.load_state_dict(old)
    assert twin.next_due() == t_split + 112 * DAY and bool((twin._meter_t == never).all())
    # B's MPFM appears: its refits end
    times = pd.DatetimeIndex(frame["time"]).as_unit("ns").asi8
    full = FrameMemory(frame, every, wells)
    t_b = int(times[is_b & mpfm & (times > t_split + 100 * DAY)].min())
    method.on_measurement(_one_row(full, 1, t_b))
    assert method._refresh_at.tolist() == [never, never] and method.next_due() is None
    # A's meter fails: a well test 30 days after its last MPFM reading starts its refits
    a_mpfm = int(method._meter_t[0, 0])
    tests = ~is_b & (frame["source"] == "well_test").to_numpy() & every
    t_a = int(times[tests & (times > a_mpfm + 31 * DAY)].min())
    method.on_measurement(_one_row(full, 0, t_a))
    assert method._refresh_at.tolist() == [t_a + 14 * DAY, never]


def test_an_mpfm_well_under_auto_is_the_filter_without_refits() -> None:
    """A hybrid well that has an MPFM: ``auto``'s study is plain ``bayes`` (refresh=off),
    the predictions the same to the bit; a well beside it without one (well tests only,
    its chokes wearing) is refitted, its lower layers moved, and it learned the wear as
    well as the filter alone (1.15 and 1.13 % here). This well starts after the split:
    before session 57 its filter started its network's output weights at the He prior on
    unfitted features (see :meth:`vfm_core.models.base.WellMLP.head_blocks`), and the
    filter alone wandered (5.9 %, the refit 1.8 %; docs/guide/bayes.md, session 51)."""
    obs = simulate_field(
        wells=2, years=2.0, seed=11, hidden=["erosion:rate=0.08"], start="2016-01-01"
    ).observations
    b = sorted(obs["well"].unique())[1]
    obs = obs[~((obs["well"] == b) & (obs["source"] == "mpfm"))].reset_index(drop=True)
    on, off = (
        run_prequential(obs, "ham", m, targets="all", split="2016-07-01")
        for m in ("bayes", "bayes:refresh=off")
    )
    assert off.updates == [] and len(on.updates) >= 5
    pa, pb = on.predictions, off.predictions
    a_on, a_off = pa[pa["well"] != b], pb[pb["well"] != b]
    assert len(a_on) > 100
    for column in ("predicted", "predicted_p05", "predicted_p95"):
        assert np.array_equal(a_on[column].to_numpy(), a_off[column].to_numpy(), equal_nan=True)
    assert on.final_model is not None and off.final_model is not None
    k = on.final_model.wells.index(b)
    w_on, w_off = (r.final_model.net.weights[0].detach() for r in (on, off))
    moved = (w_on - w_off).abs().amax(dim=(1, 2))
    assert moved[1 - k] == 0.0 and moved[k] > 1e-3, moved
    b_on, b_off = pa[pa["well"] == b], pb[pb["well"] == b]
    assert len(b_on) >= 5
    score_on = mape(b_on["predicted"], b_on["measured"])
    score_off = mape(b_off["predicted"], b_off["measured"])
    assert score_on < 1.5 and score_off < 1.5, (score_on, score_off)


def test_a_wearing_field_is_followed_better_with_the_refit() -> None:
    """Case 2 (well tests only) on a field whose chokes wear: with the shared layers as
    first fitted, the filter on the task vectors cannot follow (the error grows); refitted
    every 14 days under the filter it learns the field, about as well as ``pbl:14d``
    alone retraining (and the filter's intervals stay)."""
    field = simulate_field(
        wells=3, years=2.5, seed=11, start="2016-01-01", hidden=["erosion:rate=0.08"]
    ).observations
    runs = {
        m: run_prequential(field, "mtl", m, targets="well_test")
        for m in ("bayes:refresh=off", "bayes", "pbl:14d")
    }
    score = {
        m: mape(r.predictions["predicted"], r.predictions["measured"]) for m, r in runs.items()
    }
    on, off = runs["bayes"], runs["bayes:refresh=off"]
    # the refit ran, on the 14-day calendar from the split, and moved the shared layers
    assert off.updates == [] and len(on.updates) >= 10
    gaps = np.diff([t.value for t in on.updates])
    assert (gaps > 0).all() and (gaps % (14 * DAY) == 0).all()
    assert on.final_model is not None and off.final_model is not None
    shared_on = on.final_model.state_dict()["w_in"]
    assert (shared_on - off.final_model.state_dict()["w_in"]).abs().max() > 1e-3
    # ... and the model learned the wear: a much smaller error than without the refit
    assert score["bayes"] < 0.6 * score["bayes:refresh=off"], score
    assert score["bayes"] < 1.25 * score["pbl:14d"], score
    assert on.predictions["predicted_p95"].notna().all()


def test_the_compiled_history_pass_is_the_torch_pass() -> None:
    """The filter's start compiled (:mod:`vfm_core.learning._history_kernels`) gives the torch
    reference's state, covariance, innovations, last sensitivity and time on two thousand
    rows a well, with outliers (Huber-weighted and refused rows), gaps, a well left out of
    the start (no rows) and one with its rows at the end only."""
    kernel = bayes._history_kernel()
    if kernel is None:
        pytest.skip("the compiled kernels are off here")
    g = torch.Generator().manual_seed(5)
    n_w, n, d = 4, 2000, 9
    dtype = torch.float64
    jac = 0.3 * torch.randn(n_w, n, d, generator=g, dtype=dtype)
    log_h = torch.randn(n_w, n, generator=g, dtype=dtype)
    y = log_h + 0.03 * torch.randn(n_w, n, generator=g, dtype=dtype)
    y[:, ::97] += 0.5  # beyond the Huber point or the gate
    ok = torch.rand(n_w, n, generator=g) > 0.1
    ok[2] = False
    ok[3, :1500] = False
    time_ns = torch.cumsum(torch.randint(1, 3 * DAY, (n_w, n), generator=g), 1)
    src = (torch.rand(n_w, n, generator=g) > 0.9).long()
    noise = torch.tensor([[0.03, 0.01]] * n_w, dtype=dtype)
    prior_var = 0.1 + torch.rand(d, generator=g, dtype=dtype)
    q = 0.05 * torch.rand(d, generator=g, dtype=dtype)
    fast = bayes._history_pass(y, log_h, jac, ok, src, time_ns, noise, prior_var, q)
    p0 = bayes._history_start(ok, time_ns, prior_var, q)
    r_var = torch.gather(noise, 1, src) ** 2
    slow = bayes._history_pass_torch(y, log_h, jac, ok, time_ns, r_var, p0, q)
    names = ("m", "P", "innovations", "hph", "h_last", "t_last")
    for name, a, b in zip(names, fast, slow, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14), name
    m, P = fast[0], fast[1]
    assert (m[2] == 0).all() and torch.equal(P[2], torch.diag(p0[2]))  # untouched
    assert int(fast[5][2]) == bayes.NEVER
    assert (m[0].abs() > 1e-6).any()  # the pass moved the state of a well with rows
    z = (fast[2] / (fast[3] + r_var).sqrt()).abs()
    assert bool(((z > 3) & ok).any()) and bool(((z > 6) & ok).any())  # both rules ran


def test_a_refit_restarts_the_refitted_wells_only_as_the_differences_would(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A refit of one well of ``ham`` (its refit due, the other's not) starts that well's
    filter again, linearised by the compiled gradient at its own rows: the same start as
    the central differences over the whole field give (to their truncation error), and the
    other well's filter and parameters untouched."""
    if bayes.compiled() is None:
        pytest.skip("the compiled kernels are off here")
    frame = validate_frame(simulate_field(wells=2, years=1.0, seed=29).observations).frame
    wells = wells_of(frame)
    memory = FrameMemory(frame, target_mask(frame, "all"), wells)
    t_split = int(pd.Timestamp("2016-07-01", tz="UTC").value)
    runs = {}
    for linear in ("compiled", "differences"):
        model = make_model("ham", wells)
        method = parse_method("bayes:refresh=14d").bind(
            model, train=replace(DEFAULT_TRAIN["ham"], max_iter=60, early_stopping=False)
        )
        assert method.compiled
        method.fit(memory.batch(t_split))
        method.start(t_split)
        before = method.filter_state()[:2]
        with monkeypatch.context() as patch:
            if linear == "differences":
                patch.setattr(bayes, "compiled", lambda: None)
            now = torch.tensor([t_split + 20 * DAY, t_split + DAY])
            changed = method.retrain_due(memory, now)
        assert changed.tolist() == [True, False]
        runs[linear] = (*method.filter_state()[:2], *before)
    # theta [W, D] and P [W, D, D] after the refit, then before it
    fast, slow = runs["compiled"], runs["differences"]
    assert not torch.equal(fast[1], slow[1])  # two ways to linearise, not one
    for a, b in zip(fast, slow, strict=True):
        assert torch.allclose(a, b, rtol=1e-6, atol=1e-12)
    theta, P, theta0, P0 = fast
    assert not torch.allclose(theta[0], theta0[0]) and not torch.allclose(P[0], P0[0])
    assert torch.equal(theta[1], theta0[1]) and torch.equal(P[1], P0[1])  # not refitted
