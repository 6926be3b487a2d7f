"""Shared test setup: twin's cache (network builds, generated demand) in a temporary folder,
and the ``slow`` marker of the fast local loop.

``python -m pytest -m "not slow"`` leaves out every test that starts the CLI, SUMO or another
process, sleeps, or takes seconds of swarm runs: the modules of :data:`SLOW_MODULES` and the
tests of :data:`SLOW_TESTS`, and every ``long`` test. Put a new test of that kind in one of those
modules or name it here.
"""

from __future__ import annotations

import pytest

from twin.resources import CACHE_ENV

#: Modules whose tests run the CLI, SUMO, subprocesses, hypothesis fuzzing of the CLI, or sleep.
SLOW_MODULES = {
    "test_bad_inputs", "test_boundary", "test_cli_evaluate", "test_config_table",
    "test_experiment", "test_faults", "test_formations", "test_fuzz_readers", "test_gui",
    "test_belief_cli", "test_incidents", "test_learning_pretrain", "test_parallel_seeds", "test_replay_identity", "test_report",
    "test_resources", "test_signals", "test_slow", "test_sumo_files", "test_sumo_inputs",
    "test_sumo_network", "test_sumo_observe", "test_sumo_small", "test_sweep", "test_sweep_sumo",
    "test_timing", "test_transfer",
}  # fmt: skip
#: Tests elsewhere that take seconds (long swarm runs) or start SUMO: module::function.
SLOW_TESTS = {
    "test_ceilings::test_cli_shows_the_ceiling_rows_unless_asked_not_to",
    "test_ceilings::test_no_joint_path_beats_the_bound",
    "test_ceilings::test_no_swarm_beats_the_bound",
    "test_ceilings::test_oracle_beats_visit_gain_on_average",
    "test_ceilings::test_the_report_reads_a_run_folder_with_ceiling_rows",
    "test_ceilings::test_the_smoothed_dual_bounds_too_and_refines",
    "test_env::test_parallel_api_on_live_sumo",
    "test_planners::test_deterministic_given_the_seed",
    "test_planners::test_no_two_drones_ever_share_a_cell",
    "test_policies::test_a_swarm_does_not_depend_on_which_others_run",
    "test_policies::test_paper_pattern_on_the_evaluation_map",
    "test_policies::test_same_seed_same_numbers_and_other_seed_differs",
    "test_states::test_a_tiny_pretraining_per_variant_saves_reloads_and_evaluates",
    "test_states::test_a_bad_state_is_one_line_naming_the_key",
    "test_states::test_fine_tuning_from_a_checkpoint_of_another_state_is_refused",
    "test_states::test_a_tiny_nowcast_pretraining_saves_reloads_resumes_and_evaluates",
    "test_states::test_nowcast_refusals_are_one_line",
    "test_states::test_nowcast_pretraining_on_tapes_is_refused_in_one_line",
    "test_states::test_a_bad_dynamics_history_is_one_line",
}


def pytest_collection_modifyitems(config, items):
    for item in items:
        module = item.path.stem
        if (
            module in SLOW_MODULES
            or f"{module}::{item.originalname}" in SLOW_TESTS
            or item.get_closest_marker("long")
        ):
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session", autouse=True)
def _twin_cache(tmp_path_factory):
    """Every test, and every subprocess a test starts, builds into one fresh cache folder."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("twin-cache")))
        yield
