"""Shared test fixtures: the repo's paths and the rule for tests that need a system tool."""

from __future__ import annotations

import inspect
import os
import shutil
from pathlib import Path
from typing import NoReturn

import pytest

from wsnav.schemas.site import Site, load_site

REPO = Path(__file__).resolve().parent.parent
SITES = REPO / "sites"
SCHOOL = SITES / "school"
"""The paper's school site (map, seven zones, points A-D), the one most tests drive on."""


def require_tool(name: str) -> str:
    """Path of a system tool; skip when missing, but fail under WSNAV_REQUIRE_TOOLS=1 (CI)."""
    path = shutil.which(name)
    if path is None:
        unavailable(f"system tool {name!r} is not on PATH")
    return path


def unavailable(what: str) -> NoReturn:
    """Something the test needs from the system (a tool, root, a mount) is missing: skip, but fail under
    WSNAV_REQUIRE_TOOLS=1 (CI), where a skipped test would hide that it never ran."""
    if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
        pytest.fail(f"required (WSNAV_REQUIRE_TOOLS=1) but unavailable: {what}")
    pytest.skip(what)


pytest_plugins = ["tests.ros_fixtures", "tests.ros2_fixtures"]


@pytest.fixture(scope="module")
def school() -> Site:
    """The school site, parsed once per test module."""
    return load_site(SCHOOL)


SLOW_MODULES = {
    "test_console_browser.py",
    "test_console_intake.py",
    "test_console_log_cli.py",
    "test_compose_stack.py",
    "test_stack_processes.py",
    "test_ros_robot.py",
    "test_experiments_cluster.py",
    "test_firmware_update.py",
    "test_firmware_node.py",
    "test_firmware_ota.py",
    "test_ros2_bridge.py",
}
"""Every test here runs a process stack: docker, a browser, ROS, DDS peers, MicroPython boards, Dask processes."""
SLOW_TESTS = {
    "test_broker_credentials.py::test_mosquitto_keeps_messages_for_a_subscriber_that_stalls",
    "test_broker_protocol.py::test_fuzzed_subscribe",
    "test_broker_protocol.py::test_fuzzed_publish",
    "test_firmware_mqtt.py::test_node_waits_for_a_loaded_broker_that_answers_after_2_5_s",
    "test_broker_limits.py::test_one_node_parks_at_most_its_share_of_persistent_sessions",
    "test_broker_limits.py::test_a_flooding_node_is_held_to_its_rate_loses_nothing_and_the_other_node_gets_through",
    "test_broker_limits.py::test_a_parked_session_expires",
    "test_broker_firewall.py::test_a_flooding_node_is_held_to_its_byte_rate_and_the_other_node_gets_through",
    "test_broker_storage.py::test_mosquitto_full_disk_is_reported_at_once_and_the_last_whole_store_comes_back",
    "test_broker_limits.py::test_a_flood_stops_within_a_second_of_the_flooder_leaving_or_being_revoked",
    "test_broker_listeners.py::test_the_agents_bus_and_the_operator_commands_work_over_tls_and_refuse_a_wrong_ca",
    "test_firmware_watchdog.py::test_a_month_across_the_wraps_of_the_boards_clock",
    "test_broker_revoke.py::test_a_revoked_node_is_cut_off_and_its_retained_word_is_gone",
    "test_ros_costmap_params.py::test_roslaunch_starts_the_bridge_with_its_parameters_from_a_yaml",
    "test_ros_costmap_params.py::test_the_bridge_reads_move_bases_parameters_and_refuses_a_wrong_set_in_one_line",
    "test_broker_embedded.py::test_a_subscriber_that_never_acknowledges_costs_one_warning_line_not_a_traceback",
    "test_broker_embedded.py::test_silent_client_is_dropped_and_its_will_published",
    "test_broker_ha_discovery.py::test_the_operator_publishes_discovery_retained_and_a_node_cannot",
    "test_broker_lockout.py::test_a_full_broker_makes_room_for_a_login_by_closing_idle_sockets",
    "test_broker_lockout.py::test_a_socket_that_never_sends_connect_is_dropped_within_seconds",
    "test_broker_lockout.py::test_a_stolen_credential_cannot_fill_the_slots_with_logins",
    "test_broker_lockout.py::test_idle_sockets_and_churn_never_lock_a_node_out",
    "test_broker_protocol.py::test_fuzzed_bytes_after_login",
    "test_broker_security.py::test_refused_client_cannot_hijack_a_connected_clients_id",
    "test_broker_storage.py::test_full_disk_is_loud_loses_nothing_while_running_and_counts_what_is_lost",
    "test_experiments_run.py::test_a_row_of_the_published_experiment_comes_out_again_to_the_digit",
    "test_experiments_run.py::test_a_run_on_its_own_mosquitto_gives_the_row_and_path_it_gives_on_amqtt",
    "test_experiments_report.py::test_the_published_report_is_what_its_runs_table_renders_to",
    "test_experiments_run.py::test_a_recorded_run_keeps_every_pose_plan_zone_message_and_event_with_its_time_and_drives_the_same",
    "test_experiments_run.py::test_one_run_per_route_and_config_arrives_without_collisions_and_repeats_with_the_seed",
    "test_firmware_mqtt.py::test_keepalive_pings_are_sent_by_the_node",
    "test_firmware_mqtt.py::test_missing_pingresp_is_detected",
    "test_fleet.py::test_an_agent_keeps_others_fresh_poses_only_and_drops_bad_statuses",
    "test_fleet.py::test_two_robots_meeting_head_on_in_a_corridor_both_arrive_apart_and_the_later_one_says_it_yields",
    "test_fleet_cli.py::test_fleet_experiment_writes_its_table_report_and_trails",
    "test_fleet_cli.py::test_fleet_runs_all_ten_robots_of_the_school_and_sends_the_goals_given",
    "test_healthcheck_mqtt.py::test_broker_check_needs_a_working_login",
    "test_healthcheck_mqtt.py::test_nodes_check_names_the_nodes_not_online",
    "test_healthcheck_mqtt.py::test_robot_check_wants_a_live_status_not_a_retained_one",
    "test_plan_cli.py::test_bad_input_is_one_line_on_stderr",
    "test_plan_cli.py::test_bad_site_and_unwritable_png_are_one_line",
    "test_robot_agent_cli.py::test_a_goal_in_a_blocked_zone_exits_1_with_the_reason",
    "test_robot_agent_cli.py::test_bad_input_is_one_line_and_exit_2",
    "test_robot_agent_cli.py::test_ctrl_c_and_sigterm_stop_the_robot_cleanly",
    "test_robot_agent_cli.py::test_robot_drives_to_a_near_goal_in_real_time_and_exits_0_on_arrival",
    "test_robot_agent_e2e.py::test_every_way_blocked_waits_then_resumes_by_itself_when_a_zone_clears",
    "test_robot_agent_e2e.py::test_z4_blocked_before_the_start_the_robot_plans_around_it_and_reaches_b",
    "test_robot_agent_e2e.py::test_forged_statuses_and_goals_are_logged_once_per_kind_then_summed_up_with_a_count",
    "test_robot_agent_e2e.py::test_a_broker_outage_is_said_once_with_the_stale_policy_and_its_end_once",
    "test_robot_agent_e2e.py::test_z4_blocked_while_driving_replans_at_once_before_the_lidar_could_see_it",
    "test_robot_agent_escape.py::test_a_robot_in_a_zone_that_becomes_blocked_leaves_it_by_the_near_end_and_goes_round_to_its_goal",
    "test_robot_agent_escape.py::test_with_the_only_way_on_through_the_zone_the_robot_leaves_it_and_waits_outside_until_it_clears",
    "test_robot_agent_navigation.py::test_without_the_zone_layer_the_lidar_finds_the_obstacle_and_the_blocked_controller_replans",
    "test_ros_bridge_faults.py::test_a_site_whose_map_is_not_the_robots_is_refused_in_one_line",
    "test_ros_bridge_faults.py::test_the_bridge_comes_back_when_the_master_is_restarted",
    "test_ros_bridge_grid.py::test_the_static_layer_grid_equals_the_zone_layer_after_100_random_events",
    "test_ros_bridge_move_base.py::test_a_goal_in_a_blocked_zone_is_cancelled_whoever_sent_it",
    "test_ros_bridge_move_base.py::test_a_zone_on_the_plan_makes_move_base_replan_at_once",
    "test_runtime_bus.py::test_abort_publishes_the_will_and_a_restarted_broker_gets_the_subscriptions_again",
    "test_site_check.py::test_render_draws_the_site",
    "test_zone_sim_cli.py::test_zones_block_runs_the_nodes_and_a_robot_sees_the_zone_blocked",
    "test_zone_sim_failures.py::test_a_hung_node_is_dropped_by_the_broker_after_one_and_a_half_keepalives",
    "test_zone_sim_failures.py::test_a_killed_node_goes_stale_and_offline_and_comes_back_after_a_reboot",
    "test_zone_sim_scenarios.py::test_a_scripted_obstacle_gives_clear_blocked_clear_on_the_zones_nodes_and_leaves_it_retained",
    "test_zone_sim_scenarios.py::test_the_same_seed_gives_the_same_run_and_another_seed_another_raffle",
}
"""Tests that took over 1.5 s in a full run (brokers and processes of their own, real-time drives); a new slow
test may say `@pytest.mark.slow` itself instead."""


STARTS_A_PROCESS = (
    "BrokerProcess(",
    "Popen(",
    "subprocess.",
    "LocalRosCore(",
    "WsnavChild(",
    "NodeProcess(",
    "Board(",
    "DaskCluster(",
    "docker_daemon(",
    "playwright",
)
"""What a fixture's own code calls when it starts a real process (a broker, roscore, MicroPython, Dask, docker, a
browser): a test using such a fixture, directly or through other fixtures, is slow."""


def _starts_a_process(fixture: object) -> bool:
    try:
        source = inspect.getsource(fixture)  # type: ignore[arg-type]
    except (OSError, TypeError):
        return False
    return any(call in source for call in STARTS_A_PROCESS)


def _calls_a_starter(function: object) -> bool:
    """The test calls, by name, a function of the test suite (its module's or a shared fixture module's) that
    starts a process (`wsnav(...)`-style helpers running the command line: a test that starts processes through
    them is no faster than one doing it itself)."""
    code = getattr(function, "__code__", None)
    module = inspect.getmodule(function)  # type: ignore[arg-type]
    if code is None or module is None:
        return False
    helpers = (getattr(module, name, None) for name in code.co_names)
    return any(
        inspect.isfunction(h) and h.__module__.startswith("tests.") and _starts_a_process(h) for h in helpers
    )


def _slow_fixtures(item: pytest.Item) -> list[str]:
    """The fixtures of the item's closure that start a process."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return []
    return [
        name for name, defs in info.name2fixturedefs.items() if any(_starts_a_process(d.func) for d in defs)
    ]


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """`make test-fast` (`-m "not slow"`) runs the rest: the logic. Slow: a test that starts a process itself,
    through a helper of the suite or through its fixtures (derived from their code, `STARTS_A_PROCESS`), and the hand-kept SLOW_MODULES and
    SLOW_TESTS (processes started through helpers, or long without one)."""
    for item in items:
        module = item.path.name
        if (
            module in SLOW_MODULES
            or f"{module}::{item.originalname}" in SLOW_TESTS  # type: ignore[attr-defined]
            or _slow_fixtures(item)
            or _starts_a_process(getattr(item, "function", None))
            or _calls_a_starter(getattr(item, "function", None))
        ):
            item.add_marker(pytest.mark.slow)
