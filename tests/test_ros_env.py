"""Finding the ROS master: one clear line and backoff when there is none, found once roscore is up."""

from __future__ import annotations

import pytest

from tests.ros_fixtures import RosMaster
from wsnav.ros_bridge.ros_env import free_port, master_alive, wait_for_master
from wsnav.runtime.cli_support import CliError


def test_no_master_says_one_line_and_backs_off() -> None:
    uri = f"http://127.0.0.1:{free_port()}"
    said: list[str] = []
    slept: list[float] = []
    with pytest.raises(CliError, match="no ROS master at"):
        wait_for_master(uri, say=said.append, give_up_after_s=20, sleep=slept.append)
    assert len(said) == 1 and "retrying with backoff" in said[0]
    assert slept == [0.5, 1.0, 2.0, 4.0, 8.0, 8.0]


def test_a_running_roscore_is_found(roscore: RosMaster) -> None:
    said: list[str] = []
    assert master_alive(roscore.uri)
    wait_for_master(roscore.uri, say=said.append, give_up_after_s=0)
    assert said == []
