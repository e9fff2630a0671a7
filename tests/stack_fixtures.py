"""Shared by several test modules."""

from __future__ import annotations

import contextlib
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import yaml

from tests.broker_fixtures import wait_listening
from tests.conftest import SITES
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.process import free_port
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas import topics
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.messages import NodeStatus, PayloadError, RobotStatus, parse_payload
from wsnav.schemas.site import load_site

SITE = "sandbox_lanes"


ROBOT = "robot1"


UPPER = [[-0.3, 0.2], [0.3, 0.2], [0.3, 0.95], [-0.3, 0.95]]


LOWER = [[-0.3, -0.95], [0.3, -0.95], [0.3, -0.2], [-0.3, -0.2]]


P1 = (-2.0, 0.0, 0.0)


P2 = (2.0, 0.0, 3.1416)


def write_site(directory: Path) -> Path:
    """The TurtleBot3 sandbox (a real Nav2 map) with two zones closing the lanes beside the centre pillar."""
    directory.mkdir(parents=True)
    for name in ("tb3_sandbox.yaml", "tb3_sandbox.pgm"):
        shutil.copy(SITES / "nav2_maps" / name, directory / name)
    site = {
        "name": SITE,
        "map": "tb3_sandbox.yaml",
        "heartbeat_s": 2.0,
        "zones": [{"id": "upper", "polygon": UPPER}, {"id": "lower", "polygon": LOWER}],
        "nodes": [
            {"id": "s1", "zone": "upper", "sensor": {"type": "ir_beam", "pin": 4}},
            {"id": "s2", "zone": "lower", "sensor": {"type": "pir", "pin": 5}},
        ],
        "robots": [{"id": ROBOT, "footprint_radius": 0.105}],
        "points": {"P1": list(P1), "P2": list(P2)},
        "routes": [{"from": "P1", "to": "P2", "raffle": [["upper"], ["lower"]]}],
    }
    (directory / "site.yaml").write_text(yaml.safe_dump(site, sort_keys=False))
    # The containers run as an unprivileged user: the mounted site must be readable by others.
    directory.chmod(0o755)
    for path in directory.iterdir():
        path.chmod(0o644)
    return directory


def inside(polygon: list[list[float]], x: float, y: float) -> bool:
    """Ray casting; the zones here are convex and small, so this is exact enough."""
    hit = False
    for (x1, y1), (x2, y2) in zip(polygon, polygon[1:] + polygon[:1], strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            hit = not hit
    return hit


WSNAV = [sys.executable, "-m", "wsnav.cli"]


HEARTBEAT_S = 1.0


def make_site(directory: Path, stale: str = "keep") -> Path:
    """The sandbox site with a short heartbeat and the given stale policy."""
    site = write_site(directory)
    path = site / "site.yaml"
    spec = yaml.safe_load(path.read_text())
    spec["heartbeat_s"] = HEARTBEAT_S
    spec["policy"] = {"stale": stale}
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return site


class Proc:
    """A wsnav (or other) process whose output goes to a log file, printed when a test fails."""

    def __init__(self, name: str, args: list[str], log_dir: Path) -> None:
        self.name = name
        self.args = args
        self.log = log_dir / f"{name}-{uuid.uuid4().hex[:6]}.log"
        self._out: IO[bytes] = self.log.open("wb")
        self.popen = subprocess.Popen(
            args, stdout=self._out, stderr=subprocess.STDOUT, start_new_session=True
        )

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def alive(self) -> bool:
        return self.popen.poll() is None

    def kill9(self) -> None:
        self.popen.kill()
        self.popen.wait(30)

    def stop(self) -> None:
        if self.alive():
            self.popen.terminate()
            try:
                self.popen.wait(20)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(20)
        self._out.close()

    def wait(self, timeout_s: float) -> int:
        return self.popen.wait(timeout_s)


@dataclass
class Stack:
    """The processes of one test and what the operator saw of them."""

    site: Path
    creds: Path
    work: Path
    host: str = "127.0.0.1"
    port: int = field(default_factory=free_port)
    procs: list[Proc] = field(default_factory=list)
    statuses: list[tuple[float, RobotStatus]] = field(default_factory=list)
    nodes: list[tuple[float, NodeStatus]] = field(default_factory=list)
    observer: MqttBus | None = None

    @property
    def broker_addr(self) -> str:
        return f"{self.host}:{self.port}"

    def start(self, name: str, args: list[str]) -> Proc:
        proc = Proc(name, args, self.work)
        self.procs.append(proc)
        return proc

    def broker(self) -> Proc:
        proc = self.start(
            "broker",
            [
                *WSNAV,
                "broker",
                "run",
                "--site",
                str(self.site),
                "--credentials",
                str(self.creds),
                "--bind",
                self.broker_addr,
                "--data",
                str(self.work / "broker-data"),
            ],
        )
        wait_listening(self.host, self.port)
        return proc

    def zones(self, *what: str) -> Proc:
        return self.start(
            "zones",
            [
                *WSNAV,
                "zones",
                "--site",
                str(self.site),
                "--broker",
                self.broker_addr,
                "--credentials",
                str(self.creds),
                *what,
            ],
        )

    def robot(self, *extra: str, prefix: tuple[str, ...] = (), broker: str | None = None) -> Proc:
        return self.start(
            "robot",
            [
                *prefix,
                *WSNAV,
                "robot",
                "--site",
                str(self.site),
                "--broker",
                broker or self.broker_addr,
                "--credentials",
                str(self.creds / f"{ROBOT}.json"),
                "--sim",
                "--start",
                "P1",
                *extra,
            ],
        )

    def watch(self) -> None:
        """The operator's view: the robot's status and the nodes' births and wills (the bus reconnects itself)."""
        creds = load_credentials(self.creds / "operator.json")
        bus = MqttBus(
            self.host,
            self.port,
            client_id=f"stack-test-operator-{uuid.uuid4().hex[:6]}",
            username=creds.username,
            password=creds.password,
        )
        self.observer = bus.connect(timeout_s=30)
        bus.subscribe(topics.robot_status(SITE, ROBOT))
        bus.subscribe(topics.all_node_statuses(SITE))

    def pump(self, timeout_s: float = 0.3) -> None:
        assert self.observer is not None
        self.observer.wait(timeout_s)
        now = time.time()  # the site clock: statuses' `t` is Unix time
        for msg in self.observer.poll():
            with contextlib.suppress(PayloadError):
                if msg.topic.endswith(f"/robots/{ROBOT}/status"):
                    self.statuses.append((now, parse_payload(RobotStatus, msg.payload)))
                else:
                    self.nodes.append((now, parse_payload(NodeStatus, msg.payload)))

    def until(self, what: str, done: Callable[[], bool], timeout_s: float = 60.0) -> None:
        """Pump the operator's messages until `done()`; fail naming `what` (robot death fails at once)."""
        deadline = time.monotonic() + timeout_s
        while not done():
            assert time.monotonic() < deadline, f"timed out waiting for: {what}"
            for proc in self.procs:
                if proc.name == "robot" and not proc.alive() and proc.popen.returncode != 0:
                    raise AssertionError(f"robot exited {proc.popen.returncode} while waiting for: {what}")
            self.pump()

    def latest(self) -> RobotStatus | None:
        return self.statuses[-1][1] if self.statuses else None

    def drive_statuses(self) -> list[RobotStatus]:
        return [s for _, s in self.statuses if s.goal == "P2"]

    def stop_all(self) -> None:
        if self.observer is not None:
            self.observer.close()
        for proc in reversed(self.procs):
            proc.stop()

    def dump(self) -> str:
        return "\n".join(f"---- {p.name}: {' '.join(p.args)}\n{p.output()[-4000:]}" for p in self.procs)


@contextlib.contextmanager
def stack_on(site: Path, work: Path, host: str = "127.0.0.1") -> Iterator[Stack]:
    creds = work / "creds"
    write_credentials(load_site(site).spec, creds)
    stack = Stack(site, creds, work, host=host)
    try:
        yield stack
    except BaseException:
        stack.stop_all()
        print(stack.dump(), file=sys.stderr)
        raise
    finally:
        stack.stop_all()
