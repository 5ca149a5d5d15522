"""Shared test set-up: one torch thread, as the `vfm` command and the service use; and the
``slow`` marker on the long end-to-end tests.

The VFM's tensors are small; on a machine shared with other work a second thread's
barriers make tests many times slower; and glibc's malloc set to keep freed memory for the
next step (see vfm_core.runtime).

Which tests are slow is said here, in one place, from measured durations (``pytest -n 2
--dist loadfile --durations=60`` on the whole suite): ``make test-fast`` (``-m "not slow"``)
leaves them out for the inner loop, ``make test`` (what CI runs) runs everything.
``tests/test_layout.py`` checks that every entry still names a file or a test.
"""

from __future__ import annotations

import pytest

from vfm_core.runtime import configure

configure(1)

#: test files whose tests are all slow (end-to-end: spawned processes, a browser, the demo,
#: a whole study behind each report test); measured 2026-11-26 on the 2-core machine shared
#: with three other jobs (load 9-10): each of their tests took 15-190 s there
SLOW_FILES: frozenset[str] = frozenset(
    {
        "test_workers.py",  # spawned study workers: 120-130 s a test under load
        "test_page_browser.py",  # the workbench in chromium: 150 s
        # the other pages in chromium (a served field each; 3:06 for the fast tier's 1,009
        # tests with them on 2026-11-26 09:46 UTC, a quiet machine)
        "test_page_faults_browser.py",
        "test_well_test_review_browser.py",
        "test_service_separator_browser.py",
        "test_demo_effects.py",  # vfm demo end to end: 107 s
        "test_service_demo_signals.py",  # the demo stopped by signals: 57 s each
        "test_report.py",  # a study per report test: 15-28 s of set-up each
        "test_bayes_calibration_compiled.py",  # compiled against reference filters: 30-40 s
        # vfm serve and Debian's Prometheus, an alert firing and resolving: 26-32 s
        "test_prometheus_real.py",
        # a real vfm serve attacked over Zenoh and HTTP (its rig: 105 s of set-up, 140 s in all
        # in the fast tier's run of 2026-11-26 at load 9); the input rules stay fast in
        # test_service_bad_inputs.py, test_service_inputs.py and test_service_http_rules.py
        "test_service_adversarial.py",
        # separator readings through the service against the study: a study and a fitted
        # service behind each test (19 s of set-up each; the fast tier's run of 2026-11-26
        # 09:00 UTC, 3:15 for 1,026 tests with them); the offline rules stay fast in
        # test_separator.py
        "test_service_separator.py",
        # the operator's loop through the service (a diagnosis over HTTP, two changes, both
        # trials to their end): 43-65 s on 2026-11-26 at load 4-6, the diagnosis most of it
        "test_service_rollback_live.py",
    }
)

#: single slow tests, ``file::name`` (every parametrisation of the test): those above 30 s
#: in that run (and their kin, the same test's other parametrisations)
SLOW_TESTS: frozenset[str] = frozenset(
    {
        "test_service_workbench.py::test_diagnosis_job_lifecycle",  # 187 s
        "test_service_adversarial.py::test_kill9_at_several_moments",  # 120 s
        # sums up the file's figures, the acknowledgements the kill -9 test checks among them
        "test_service_adversarial.py::test_figures",
        "test_service_restart.py::test_kill9_and_restart_keep_state_and_data",  # 62 s
        "test_service_scaleout.py::test_two_instances_share_a_field_and_one_keeps_serving_when_the_other_dies",  # 50 s
        "test_service_trial.py::test_the_loop_keeps_a_good_change_and_rolls_back_a_wrong_one",  # 45 s
        "test_bayes.py::test_an_added_effect_keeps_its_strength_for_a_year",  # 82 s
        "test_bayes.py::test_an_added_effect_keeps_its_strength_through_the_service",  # 58 s
        "test_runtime.py::test_training_memory_stays_in_the_process_unless_told_otherwise",  # 63 s
        "test_tune_drift_cli.py::test_tune_is_resumable_and_chooses_from_the_grid",  # 34 s
        "test_effects.py::test_streaming_learner_with_an_effect_learns_the_wear",  # 20 s
        # the diagnosis on whole simulated fields: 28-124 s each
        "test_diagnose.py::test_base_effects_turn_the_diagnosis_to_what_is_still_missing",
        "test_diagnose_library.py::test_hidden_library_effect_is_the_verdict_and_halves_the_error",
        "test_diagnose.py::test_another_implementation_of_the_physics_gets_the_valve_it_differs_by",
        "test_diagnose_library.py::test_effects_that_leave_no_trace_are_not_claimed",
        "test_diagnose_library.py::test_outputs_follow_the_contract",
        "test_diagnose.py::test_effect_outside_the_library_gets_a_driver_verdict_and_a_correction",
        "test_diagnose.py::test_noise_floor_estimate_is_close_to_the_truth",
        "test_diagnose.py::test_clean_field_is_noise_with_no_false_discovery",
        "test_diagnose.py::test_laplace_sd_agrees_with_the_spread_of_repeated_fits",
        "test_diagnose.py::test_store_end_to_end",
        "test_diagnose.py::test_a_users_own_effect_removes_what_the_driver_named",
        # above 30 s in the first run of the fast tier (8:57 under the same load)
        "test_diagnose.py::test_the_suggestion_applies_directly_in_evaluate",  # 38 s
        "test_diagnose_library.py::test_progress_is_reported_as_a_fraction_with_a_text",  # 36 s
        "test_diagnose.py::test_json_is_plain_and_finite",  # 32 s
        "test_diagnose_replay.py::test_a_wells_diagnosis_stands_beside_its_pool",  # 82 s
        "test_diagnose_replay.py::test_the_live_baseline_is_the_replay_of_the_wells_method",  # 59 s
        # and in the second (8:14)
        "test_diagnose_replay.py::test_strong_wear_is_the_verdict_with_intervals_and_evidence",  # 46 s
        "test_diagnose.py::test_report_of_a_driver_verdict_shows_the_correction",  # 36 s
        # the fast tier's run of 2026-11-26 04:38 UTC (9:37 for 871 tests at load 9; 3:13 before)
        "test_diagnose_replay.py::test_a_candidate_that_raises_the_error_is_never_offered",  # 173 s
        "test_service_model_change.py::test_model_change_over_http",  # 37 s, a serve and a refit
        "test_diagnose.py::test_command_line_end_to_end",  # 21 s, vfm diagnose in a subprocess
        # five replays of a wearing well (issue 36's trial forecast), 35-45 s under load
        "test_diagnose_live.py::test_on_a_wearing_well_the_trial_forecast_sees_the_gain_the_whole_history_hides",
    }
)

#: slow parametrisations, ``(file::name, part of the id)``: the model contract of mm with
#: each effect (vfm_core.checks.check_effect_model_contract), 5-24 s each under that load
#: (2-4 s in a run of the file alone); the effects' other checks stay in the fast tier
SLOW_CASES: frozenset[tuple[str, str]] = frozenset(
    {
        ("test_effects.py::test_effect_contract", "-model_contract]"),
        # a new well in the service against the study: 17 s each at load 9 (hem and nn with
        # ol); hem with pbl:60d (11 s) keeps the check in the fast tier
        ("test_service_new_well.py::test_a_new_well_starts_as_in_the_study", "-ol]"),
    }
)


#: the files that take longest (their tests' sum, from the same kind of measurement: the
#: slow tier at load 6-8 on 2026-11-27, 02:57-03:43 UTC), longest first: they are collected
#: first, so that ``make test`` (``--dist loadfile --no-loadscope-reorder``: each process
#: takes the next file in collection order) starts them at once instead of leaving one to
#: run alone at the end; the other files follow in their usual order
LONGEST_FIRST: tuple[str, ...] = (
    "test_diagnose.py",
    "test_diagnose_library.py",
    "test_diagnose_replay.py",
    "test_service_adversarial.py",
    "test_bayes.py",
    "test_page_browser.py",
    "test_service_rollback_live.py",
    "test_workers.py",
    "test_bayes_calibration_compiled.py",
    "test_service_scaleout.py",
    "test_service_separator.py",
    "test_service_workbench.py",
    "test_service_demo_signals.py",
    "test_demo_effects.py",
    "test_service_restart.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {file: k for k, file in enumerate(LONGEST_FIRST)}
    # a stable sort: each file's tests keep their order (module fixtures are shared in it)
    items.sort(key=lambda item: rank.get(item.nodeid.partition("::")[0].rpartition("/")[2], 99))
    slow = pytest.mark.slow
    for item in items:
        path, _, name = item.nodeid.partition("::")
        file = path.rpartition("/")[2]
        test = f"{file}::{name.partition('[')[0]}"
        if (
            file in SLOW_FILES
            or test in SLOW_TESTS
            or any(test == t and part in name for t, part in SLOW_CASES)
        ):
            item.add_marker(slow)


@pytest.fixture
def predict_block_calls(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The row count of every block prediction call the service's engine makes
    (``Learning.predict_block``, wrapped; the calls still run)."""
    from service.engine.learning import Learning

    calls: list[int] = []
    predict_block = Learning.predict_block

    def counted(self: Learning, st: object, inputs: object, times_ns: object) -> object:
        calls.append(len(times_ns))  # type: ignore[arg-type]
        return predict_block(self, st, inputs, times_ns)  # type: ignore[arg-type]

    monkeypatch.setattr(Learning, "predict_block", counted)
    return calls
