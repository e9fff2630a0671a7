"""The whole stack in containers (docker-compose.yml), driven from the host over MQTT as an operator would.

The harness starts Debian's dockerd when none runs (as root), builds the local base image when missing
(docker/build-base-image), prefetches the pinned wheels with the host's pip (docker/prefetch-wheels: the
containers may not reach PyPI themselves), builds the image, starts the stack on a site over a real Nav2 map
(the TurtleBot3 sandbox, so the drive takes seconds, not minutes), blocks a lane through the zone simulator,
sends the robot a goal over the published broker port and follows its status until it arrives. Containers,
network and volumes are removed at the end; the images stay, so a second run takes a fraction of the first.
On failure the containers' logs are printed.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.conftest import REPO, require_tool
from tests.stack_fixtures import P2, ROBOT, SITE, UPPER, inside, write_site
from wsnav.broker.mosquitto.process import free_port
from wsnav.runtime.mqtt_bus import BusError, MqttBus
from wsnav.schemas import topics
from wsnav.schemas.messages import PayloadError, RobotGoal, RobotStatus, parse_payload

pytestmark = pytest.mark.timeout(1500)

BASE_IMAGE = os.environ.get("WSNAV_TEST_BASE_IMAGE", "wsnav-base:bookworm")
IMAGE = "wsnav:compose-test"
# The sandbox's pillars stand in three rows; the direct way from P1 to P2 runs between the middle and the top
# row. `upper` closes that lane at the centre pillar; the robot must take the lane below the middle row.


def unavailable(reason: str) -> None:
    """Skip, or fail under WSNAV_REQUIRE_TOOLS=1 (CI), like conftest.require_tool."""
    if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
        pytest.fail(f"{reason} (WSNAV_REQUIRE_TOOLS=1)")
    pytest.skip(reason)


class Progress:
    """Lines to the terminal while pytest captures output: the cold build takes minutes."""

    def __init__(self, config: pytest.Config) -> None:
        capture = config.pluginmanager.getplugin("capturemanager")
        self._uncaptured = getattr(capture, "global_and_fixture_disabled", contextlib.nullcontext)
        self.started = time.monotonic()

    def __call__(self, text: str) -> None:
        with self._uncaptured():
            print(
                f"[compose test {time.monotonic() - self.started:6.1f} s] {text}", file=sys.stderr, flush=True
            )


def run_logged(
    args: Sequence[str],
    log: Path,
    progress: Progress,
    *,
    echo: Sequence[str] = (),
    timeout_s: float,
    env: dict[str, str] | None = None,
) -> None:
    """Run a long command, output to `log`; lines starting with one of `echo` are shown as progress."""
    progress(f"$ {' '.join(args)}")
    with log.open("a") as out:
        proc = subprocess.Popen(
            list(args), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=REPO
        )
        watchdog = threading.Timer(timeout_s, proc.kill)
        watchdog.start()
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                out.write(line)
                if any(line.startswith(prefix) for prefix in echo):
                    progress("  " + line.rstrip())
            code = proc.wait()
        finally:
            watchdog.cancel()
    if code != 0:
        tail = "".join(log.read_text().splitlines(keepends=True)[-60:])
        pytest.fail(f"{args[0]} exited {code} (log {log}):\n{tail}")


def docker_ready() -> bool:
    return subprocess.run(["docker", "info"], capture_output=True, timeout=30).returncode == 0


@pytest.fixture(scope="module")
def progress(pytestconfig: pytest.Config) -> Progress:
    return Progress(pytestconfig)


@pytest.fixture(scope="module")
def docker_daemon(tmp_path_factory: pytest.TempPathFactory, progress: Progress) -> Iterator[None]:
    """A reachable Docker daemon: the running one, or Debian's dockerd started here (and stopped after)."""
    require_tool("docker")
    require_tool("docker-compose")
    if docker_ready():
        yield
        return
    if os.geteuid() != 0 or shutil.which("dockerd") is None:
        unavailable(
            "no Docker daemon is running and this user cannot start dockerd (needs root and docker.io)"
        )
    log = tmp_path_factory.mktemp("dockerd") / "dockerd.log"
    progress(f"starting dockerd (log {log})")
    with log.open("w") as out:
        daemon = subprocess.Popen(["dockerd"], stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not docker_ready():
            if daemon.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"dockerd did not start:\n{log.read_text()[-3000:]}")
            time.sleep(0.5)
        yield
    finally:
        daemon.terminate()
        try:
            daemon.wait(60)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait(30)


@pytest.fixture(scope="module")
def image(docker_daemon: None, tmp_path_factory: pytest.TempPathFactory, progress: Progress) -> str:
    """The wsnav image built on the local base image (both cached across runs by Docker itself)."""
    logs = tmp_path_factory.mktemp("build")
    have_base = (
        subprocess.run(["docker", "image", "inspect", BASE_IMAGE], capture_output=True).returncode == 0
    )
    if not have_base:
        if os.geteuid() != 0:
            unavailable(f"base image {BASE_IMAGE} missing and building it (debootstrap) needs root")
        require_tool("debootstrap")
        run_logged(
            [str(REPO / "docker" / "build-base-image"), BASE_IMAGE],
            logs / "base.log",
            progress,
            echo=("[", "  ", "E:", "W:"),
            timeout_s=900,
        )
    build_args = ["--build-arg", f"BASE={BASE_IMAGE}"]
    if sys.version_info[:2] == (3, 11):
        run_logged(
            [str(REPO / "docker" / "prefetch-wheels"), sys.executable],
            logs / "wheels.log",
            progress,
            echo=("prefetch-wheels:",),
            timeout_s=600,
        )
        build_args += ["--build-arg", "PIP_NO_INDEX=1"]
    env = dict(os.environ, WSNAV_IMAGE=IMAGE)
    run_logged(
        ["docker-compose", "-f", str(REPO / "docker-compose.yml"), "build", *build_args, "broker"],
        logs / "build.log",
        progress,
        echo=("Step ", "Successfully tagged"),
        timeout_s=900,
        env=env,
    )
    return IMAGE


def crosses(polygon: list[list[float]], path: list[list[float]], step_m: float = 0.02) -> bool:
    """Whether the polyline enters the polygon (a smoothed plan has few vertices: walk its segments)."""
    for (x1, y1), (x2, y2) in itertools.pairwise(path):
        n = max(1, int(((x2 - x1) ** 2 + (y2 - y1) ** 2) ** 0.5 / step_m))
        if any(inside(polygon, x1 + (x2 - x1) * i / n, y1 + (y2 - y1) * i / n) for i in range(n + 1)):
            return True
    return False


def offline_plan(site: Path, *blocked: str) -> list[list[float]]:
    args = [sys.executable, "-m", "wsnav.cli", "plan", "--site", str(site), "--from", "P1", "--to", "P2"]
    for zone in blocked:
        args += ["--block", zone]
    out = subprocess.run(args, capture_output=True, text=True, timeout=120, check=True)
    result = json.loads(out.stdout)
    assert result["reachable"]
    return result["path"]


@dataclass
class Stack:
    """One compose project: its own name, network, volumes and host port."""

    project: str
    site: Path
    port: int
    env: dict[str, str] = field(default_factory=dict)

    def compose(self, *args: str, timeout_s: float = 300, check: bool = True) -> str:
        cmd = ["docker-compose", "-p", self.project, "-f", str(REPO / "docker-compose.yml"), *args]
        done = subprocess.run(cmd, capture_output=True, text=True, env=self.env, cwd=REPO, timeout=timeout_s)
        if check and done.returncode != 0:
            raise AssertionError(f"{' '.join(cmd)} exited {done.returncode}:\n{done.stdout}{done.stderr}")
        return done.stdout

    def logs(self) -> str:
        return self.compose("logs", "--no-color", "--timestamps", check=False, timeout_s=120)

    def health(self, service: str) -> str:
        container = self.compose("ps", "-q", service).strip()
        out = subprocess.run(
            ["docker", "inspect", "--format", "{{.State.Health.Status}}", container],
            capture_output=True,
            text=True,
            timeout=60,
        )
        return out.stdout.strip()

    def credentials(self, ident: str) -> dict[str, str]:
        """A generated credentials file, read from the volume through the broker's container."""
        return json.loads(self.compose("exec", "-T", "broker", "cat", f"/creds/{ident}.json"))

    def bus(self, ident: str, password: str | None = None) -> MqttBus:
        creds = self.credentials(ident)
        return MqttBus(
            "127.0.0.1",
            self.port,
            client_id=f"compose-test-{ident}-{uuid.uuid4().hex[:6]}",
            username=creds["username"],
            password=password if password is not None else creds["password"],
        )


@contextlib.contextmanager
def logs_on_failure(stack: Stack) -> Iterator[None]:
    try:
        yield
    except BaseException:
        print(f"---- docker-compose logs ({stack.project}) ----\n{stack.logs()}", file=sys.stderr)
        raise


@pytest.fixture(scope="module")
def stack(image: str, tmp_path_factory: pytest.TempPathFactory, progress: Progress) -> Iterator[Stack]:
    site = write_site(tmp_path_factory.mktemp("compose") / "site")
    port = free_port()
    env = dict(
        os.environ,
        WSNAV_IMAGE=image,
        WSNAV_BASE=BASE_IMAGE,
        WSNAV_SITE=str(site),
        WSNAV_MQTT_HOST="127.0.0.1",
        WSNAV_MQTT_PORT=str(port),
        WSNAV_CONSOLE_PORT=str(free_port()),  # the console service: a free host port, never a fixed 8080
        WSNAV_ZONES="--block upper",
        WSNAV_START="P1",
        WSNAV_ROBOT_ARGS="--config full",  # no --goal: the test sends it over MQTT
    )
    running = Stack(f"wsnavtest{os.getpid()}{uuid.uuid4().hex[:6]}", site, port, env)
    progress(f"docker-compose up ({running.project}, broker on 127.0.0.1:{port})")
    try:
        with logs_on_failure(running):
            running.compose("up", "-d", "--no-build", timeout_s=300)
        progress("stack up: " + ", ".join(f"{s} {running.health(s)}" for s in ("broker", "zones", "robot")))
        yield running
    finally:
        progress("docker-compose down -v")
        running.compose("down", "-v", "--remove-orphans", "--timeout", "20", check=False, timeout_s=300)


def test_the_lane_matters_on_this_site(tmp_path: Path) -> None:
    """Guard for the drive below: without the block the plan runs through `upper`, with it it does not."""
    site = write_site(tmp_path / "site")
    assert crosses(UPPER, offline_plan(site))
    assert not crosses(UPPER, offline_plan(site, "upper"))


def test_services_are_healthy_and_the_broker_checks_passwords(stack: Stack) -> None:
    with logs_on_failure(stack):
        deadline = time.monotonic() + 60
        while (states := {s: stack.health(s) for s in ("broker", "zones", "robot")}) != dict.fromkeys(
            ("broker", "zones", "robot"), "healthy"
        ):
            assert time.monotonic() < deadline, f"not all healthy: {states}"
            time.sleep(2)
        operator = stack.bus("operator").connect(timeout_s=20)
        operator.close()
        impostor = stack.bus("operator", password="not-the-generated-password")
        with pytest.raises(BusError):
            impostor.connect(timeout_s=5)
        impostor.close()


def test_robot_avoids_the_blocked_lane_and_arrives(stack: Stack, progress: Progress) -> None:
    with logs_on_failure(stack):
        operator = stack.bus("operator").connect(timeout_s=20)
        try:
            operator.subscribe(topics.robot_status(SITE, ROBOT))
            time.sleep(1.0)  # the SUBACK: the bus subscribes asynchronously
            operator.publish(topics.robot_goal(SITE, ROBOT), RobotGoal(goal="P2").to_payload(), qos=1)
            progress("goal P2 sent; following robot1's status")
            statuses: list[RobotStatus] = []
            deadline = time.monotonic() + 240
            while time.monotonic() < deadline and not (statuses and statuses[-1].state == "arrived"):
                operator.wait(0.5)
                for msg in operator.poll():
                    with contextlib.suppress(PayloadError):
                        statuses.append(parse_payload(RobotStatus, msg.payload))
        finally:
            operator.close()
        moving = [s for s in statuses if s.goal == "P2"]
        assert moving, f"the robot never took the goal; statuses: {statuses[-3:]}"
        assert moving[-1].state == "arrived", f"last status: {moving[-1]}"
        x, y, _ = moving[-1].pose
        assert abs(x - P2[0]) < 0.3 and abs(y - P2[1]) < 0.3, f"arrived at {moving[-1].pose}, not at P2"
        assert all("upper" in s.blocked_zones for s in moving), (
            "the blocked lane was not in the robot's costmap"
        )
        assert not any("lower" in s.blocked_zones for s in moving)
        entered = [s.pose for s in moving if inside(UPPER, s.pose[0], s.pose[1])]
        assert not entered, f"the robot drove into the blocked zone at {entered[:3]}"
        assert any(s.pose[1] < -0.2 for s in moving), "the robot did not take the lane below the pillars"
        progress(f"arrived after {len(moving)} statuses, {moving[-1].replans} replans")


def test_the_console_keeps_its_state_on_a_writable_named_volume() -> None:
    """Without a writable `--state-dir` the console's sessions, event log and operator blocks lived in the
    container and were gone at every restart or upgrade (one warning line). Read from the files, no engine."""
    import yaml

    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    console = compose["services"]["console"]
    words = console["command"].split()
    assert "--state-dir" in words, "the console is given no --state-dir"
    state_dir = words[words.index("--state-dir") + 1]
    mounts = {v.split(":")[1]: v.split(":") for v in console["volumes"]}
    assert state_dir in mounts, f"{state_dir} is not a volume"
    volume = mounts[state_dir]
    assert volume[0] in compose["volumes"] and "ro" not in volume[2:], "a named, writable volume"
    dockerfile = (REPO / "docker" / "Dockerfile").read_text()
    assert f"chown 10001:10001 /home/wsnav /creds /data {state_dir}" in dockerfile, (
        "owned by the image's user"
    )
