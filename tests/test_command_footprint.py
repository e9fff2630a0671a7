"""What each command loads when it really starts (a child process, its sys.modules read at its exit): the arrows the
import test cannot see, because they run through a chain of allowed imports or a function-level one.

The ROS 2 bridge reached the agent (26 agent and navigation modules and numba, 2.6 s of CPU against 0.4 s) to check
a credentials file; a Raspberry Pi broker must not need numpy, scipy or the robot's code at all."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.conftest import SCHOOL
from tests.ros_fixtures import RosMaster, bridge_args
from wsnav.broker.amqtt.embedded import BrokerThread

pytestmark = pytest.mark.slow

WRAPPER = """
import atexit, json, signal, sys
out = sys.argv[1]
atexit.register(lambda: open(out, "w").write(json.dumps(sorted(sys.modules))))
signal.signal(signal.SIGTERM, lambda _n, _f: sys.exit(143))  # until the command sets its own
from wsnav.cli import main
sys.exit(main(sys.argv[2:]))
"""

HEAVY = ("numpy", "scipy", "numba", "pandas", "matplotlib", "pyastar2d")


def loaded_by(
    tmp_path: Path, args: list[str], ready: str, env: dict[str, str] | None = None, timeout_s: float = 60.0
) -> set[str]:
    """Start `wsnav <args>`, wait for `ready` in its output, stop it with SIGTERM, and return what it had loaded."""
    wrapper = tmp_path / "wrapper.py"
    wrapper.write_text(WRAPPER)
    out = tmp_path / "modules.json"
    proc = subprocess.Popen(
        [sys.executable, str(wrapper), str(out), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env=env,
    )
    lines: list[str] = []

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + timeout_s
        while not any(ready in line for line in lines):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"no {ready!r} from wsnav {' '.join(args)}:\n{''.join(lines)}")
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    reader.join(5)
    assert out.exists(), "".join(lines)
    return set(json.loads(out.read_text()))


def heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules if m.split(".")[0] in HEAVY and "." not in m)


def code_of(modules: set[str], *components: str) -> list[str]:
    """The modules of these wsnav components that do work: every `wsnav` command builds the whole argparse tree,
    so each component's package and its `cli` parser module load everywhere (they import no code of theirs)."""
    names = tuple(f"wsnav.{c}" for c in components)
    return sorted(m for m in modules if m.startswith(names) and m not in names and not m.endswith(".cli"))


def test_the_broker_loads_neither_numpy_nor_the_robots_code(tmp_path: Path) -> None:
    with BrokerThread(SCHOOL) as site_broker:  # writes the site's credentials folder
        creds = site_broker.credentials_dir
        modules = loaded_by(
            tmp_path,
            ["broker", "run", "--site", str(SCHOOL), "--credentials", str(creds), "--bind", "127.0.0.1:0"],
            "broker ready on",
        )
    assert "wsnav.broker.amqtt.server" in modules, "the broker really started"
    assert heavy(modules) == []
    assert code_of(modules, "navigation", "robot_agent", "zone_sim", "experiments") == []


def test_the_ros2_bridge_checks_its_credentials_without_loading_the_agent(tmp_path: Path) -> None:
    with BrokerThread(SCHOOL) as broker:
        modules = loaded_by(
            tmp_path,
            [
                "ros2",
                "bridge",
                "--site",
                str(SCHOOL),
                "--broker",
                f"{broker.host}:{broker.port}",
                "--credentials",
                str(broker.credentials_dir / "robot1.json"),
                "--domain",
                str(150 + os.getpid() % 80),
                "--log-level",
                "info",
            ],
            "MQTT broker connected",
        )
    assert "wsnav.ros2_bridge.bridge" in modules and "cyclonedds" in modules, "the bridge really started"
    assert code_of(modules, "robot_agent", "navigation") == []
    assert "numba" not in modules


def test_the_ros1_bridge_serves_its_grid_without_loading_the_agent(
    tmp_path: Path, roscore: RosMaster
) -> None:
    """It paid for the agent and numba on every start (16 s to its first line on a loaded machine while
    move_base's costmap waited for the grid)."""
    with BrokerThread(SCHOOL) as broker:
        args = ["ros", "bridge", *bridge_args(SCHOOL, broker)]
        modules = loaded_by(tmp_path, args, "zone bridge for site school", roscore.env())
    assert "rospy" in modules, "the bridge really started"
    # Algorithm 3's rule (for --robot) is pure Python: no numpy, no planner.
    assert code_of(modules, "robot_agent", "navigation") == ["wsnav.navigation.replan_policy"]
    assert "numba" not in modules
