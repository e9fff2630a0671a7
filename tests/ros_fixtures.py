"""Shared by the ROS tests (no tests here): a real `roscore` on a free port, and one rospy node for the test process.

rospy allows one node per process and binds it to one master, so the whole session shares one roscore and the
test process is one node (`ros_node`); wsnav's own ROS nodes run as child processes (`ros_env` is their
environment). Without Debian's ROS packages these fixtures skip, and fail under WSNAV_REQUIRE_TOOLS=1 (CI).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.conftest import SITES, require_tool
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.ros_env import LocalRosCore, stop_process_group
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas import topics
from wsnav.schemas.messages import RobotStatus, ZoneState


def require_ros() -> None:
    """Skip (or fail under WSNAV_REQUIRE_TOOLS=1) unless roscore and rospy are installed."""
    require_tool("roscore")
    try:
        import rospy  # noqa: F401  # pyright: ignore[reportMissingImports, reportUnusedImport]
    except ImportError:
        if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
            pytest.fail("rospy is required (WSNAV_REQUIRE_TOOLS=1) but the venv cannot import it")
        pytest.skip("rospy not importable")


@dataclass
class RosMaster:
    uri: str
    log_dir: Path
    core: LocalRosCore

    def env(self, **extra: str) -> dict[str, str]:
        """The environment of a child process that is a node of this master (loopback only)."""
        return self.core.env(**extra)


@pytest.fixture(scope="session")
def roscore(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RosMaster]:
    require_ros()
    log_dir = tmp_path_factory.mktemp("ros-logs")
    with LocalRosCore(log_dir) as core:
        yield RosMaster(core.uri, log_dir, core)


@pytest.fixture(scope="session")
def ros_node(roscore: RosMaster) -> Iterator[RosMaster]:
    """The test process as a node of the session's master (rospy: once per process).

    Shut down at the session's end: actionlib's server threads are not daemons and loop until rospy shuts down,
    and rospy's own shutdown runs at exit only after Python has waited for them, so pytest would never exit."""
    import rospy  # pyright: ignore[reportMissingImports]

    os.environ.update(ROS_MASTER_URI=roscore.uri, ROS_HOSTNAME="127.0.0.1", ROS_LOG_DIR=str(roscore.log_dir))
    rospy.init_node("wsnav_test", anonymous=True, disable_signals=True)
    yield roscore
    rospy.signal_shutdown("the test session is over")


def wait_until(condition: Callable[[], bool], timeout_s: float, what: str, step_s: float = 0.02) -> None:
    """Poll (real time) until `condition()` holds; fail the test naming `what` otherwise."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:g} s waiting for {what}")
        time.sleep(step_s)


class WsnavChild:
    """A wsnav command as a child process; its output lines are kept for the test to read."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.lines: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "wsnav.cli", *args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self._pump = threading.Thread(target=self._read, daemon=True)
        self._pump.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line.rstrip("\n"))

    def wait_for(self, text: str, timeout_s: float) -> str:
        def seen() -> bool:
            return any(text in line for line in self.lines) or self.proc.poll() is not None

        wait_until(seen, timeout_s, f"{text!r} from wsnav {self.proc.args}")
        found = [line for line in self.lines if text in line]
        assert found, "\n".join(self.lines)
        return found[0]

    def finish(self, timeout_s: float) -> int:
        try:
            code = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            stop_process_group(self.proc)
            raise AssertionError("still running:\n" + "\n".join(self.lines)) from None
        self._pump.join(5)
        return code

    def stop(self) -> None:
        stop_process_group(self.proc)
        self._pump.join(5)


def slow_heartbeat_school(directory: Path) -> Path:
    """The school site with a 10-minute heartbeat and stale nodes read as unknown (-1 on the grid)."""
    site_dir = directory / "school"
    shutil.copytree(SITES / "school", site_dir)
    spec = yaml.safe_load((site_dir / "site.yaml").read_text())
    spec["heartbeat_s"] = 600.0
    spec["policy"] = {**spec.get("policy", {}), "stale": "unknown"}
    (site_dir / "site.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    return site_dir


def bridge_args(site_dir: Path, broker: BrokerThread, *extra: str) -> list[str]:
    return [
        "--site",
        str(site_dir),
        "--broker",
        f"{broker.host}:{broker.port}",
        "--credentials",
        str(broker.credentials_dir / "robot1.json"),
        "--map-wait",
        "0",
        *extra,
    ]


@dataclass
class Operator:
    bus: MqttBus
    site: str
    statuses: list[RobotStatus] = field(default_factory=list)

    def poll(self) -> None:
        for m in self.bus.poll():
            if m.payload:
                self.statuses.append(RobotStatus.model_validate_json(m.payload))

    def latest(self) -> RobotStatus | None:
        self.poll()
        return self.statuses[-1] if self.statuses else None

    def wait_status(self, what: str, check: Any, timeout_s: float = 15.0) -> RobotStatus:
        wait_until(lambda: (s := self.latest()) is not None and bool(check(s)), timeout_s, what)
        status = self.latest()
        assert status is not None
        return status


def zone_state(bus: MqttBus, zone: str, node: str, state: str, seq: int) -> None:
    msg = ZoneState(zone=zone, node=node, state=state, seq=seq)  # type: ignore[arg-type]
    bus.publish(topics.zone_state("school", zone, node), msg.to_payload(), qos=1, retain=True)


def send_goal(operator: Operator, goal: object) -> None:
    operator.bus.publish(topics.robot_goal("school", "robot1"), json.dumps({"goal": goal}).encode(), qos=1)
