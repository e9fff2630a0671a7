"""Where ROS 1 comes from and how a wsnav ROS node finds its master.

rospy is not on PyPI: it comes from Debian's packages (`python3-rospy`, ...) in the system's dist-packages,
which the venv reads last (scripts/bootstrap-venv writes a .pth), so pinned dependencies are never shadowed.
Everything here is importable without ROS; `require_rospy` says in one line what to install when it is missing.
"""

from __future__ import annotations

import http.client
import os
import signal
import socket
import subprocess
import time
import xmlrpc.client
from collections.abc import Callable
from pathlib import Path
from types import TracebackType

from wsnav.runtime.cli_support import CliError

DEBIAN_PACKAGES = (
    "ros-core python3-rospy python3-rostopic python3-nav-msgs python3-map-msgs python3-sensor-msgs "
    "python3-geometry-msgs python3-actionlib python3-move-base-msgs python3-tf2-ros"
)
DEFAULT_MASTER_URI = "http://localhost:11311"


def say(text: str, *, warn: bool = False) -> None:
    """Log as a ROS node does: through rospy, to /rosout and the console (the node is initialised by then)."""
    import rospy  # pyright: ignore[reportMissingImports]  (Debian's, outside the venv)

    (rospy.logwarn if warn else rospy.loginfo)(text)


def require_rospy() -> None:
    """Fail with one line (not an ImportError traceback) when ROS 1's Python packages are missing."""
    try:
        import rospy  # noqa: F401  # pyright: ignore[reportMissingImports, reportUnusedImport]
    except ImportError as exc:
        raise CliError(
            f"ROS 1 is not installed ({exc.name} missing): apt-get install {DEBIAN_PACKAGES} "
            "(then rerun `make .venv/.installed-stamp` so the venv sees it)"
        ) from None


def master_uri() -> str:
    return os.environ.get("ROS_MASTER_URI", DEFAULT_MASTER_URI)


def master_alive(uri: str, timeout_s: float = 2.0) -> bool:
    """True if a ROS master answers at `uri` (its getPid call), without rospy's own long retries."""
    transport = _TimeoutTransport(timeout_s)
    try:
        answer: object = xmlrpc.client.ServerProxy(uri, transport=transport).getPid("/wsnav_probe")
    except (OSError, xmlrpc.client.Error, ValueError):
        return False
    return isinstance(answer, list) and len(answer) == 3 and answer[0] == 1  # [code, message, pid]


def master_param(uri: str, key: str, timeout_s: float = 5.0) -> object | None:
    """A parameter from the master's parameter server (a dict for a namespace), None when it is not set."""
    transport = _TimeoutTransport(timeout_s)
    answer: object = xmlrpc.client.ServerProxy(uri, transport=transport).getParam("/wsnav_bridge", key)
    if isinstance(answer, list) and len(answer) == 3 and answer[0] == 1:
        return answer[2]
    return None


def wait_for_master(
    uri: str,
    *,
    say: Callable[[str], None] = print,
    give_up_after_s: float | None = None,
    first_delay_s: float = 0.5,
    max_delay_s: float = 8.0,
    sleep: Callable[[float], None] = time.sleep,
) -> None:
    """Block until the master at `uri` answers: one line when it does not, then retries with doubling delays.

    Raises CliError after `give_up_after_s` (None: wait for ever, as a node started before roscore should).
    """
    delay = first_delay_s
    waited = 0.0
    told = False
    while not master_alive(uri):
        if give_up_after_s is not None and waited >= give_up_after_s:
            raise CliError(
                f"no ROS master at {uri} after {waited:.0f} s (is roscore running? ROS_MASTER_URI?)"
            )
        if not told:
            say(f"no ROS master at {uri} (is roscore running? ROS_MASTER_URI?): retrying with backoff")
            told = True
        sleep(delay)
        waited += delay
        delay = min(delay * 2, max_delay_s)
    if told:
        say(f"ROS master at {uri} is up")


class _TimeoutTransport(xmlrpc.client.Transport):
    def __init__(self, timeout_s: float) -> None:
        super().__init__()
        self._timeout_s = timeout_s

    def make_connection(self, host: tuple[str, dict[str, str]] | str) -> http.client.HTTPConnection:
        conn = super().make_connection(host)
        conn.timeout = self._timeout_s
        return conn


class LocalRosCore:
    """A `roscore` of our own on a free loopback port (tests, benchmarks): `with LocalRosCore(log_dir) as core`.

    `core.env()` is the environment of a child process that is one of its nodes."""

    def __init__(self, log_dir: Path, port: int | None = None, start_timeout_s: float = 30.0) -> None:
        self.log_dir = log_dir
        self.port = port if port is not None else free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self._timeout = start_timeout_s
        self.proc: subprocess.Popen[bytes] | None = None

    def env(self, **extra: str) -> dict[str, str]:
        return dict(
            os.environ,
            ROS_MASTER_URI=self.uri,
            ROS_HOSTNAME="127.0.0.1",
            ROS_LOG_DIR=str(self.log_dir),
            PYTHONUNBUFFERED="1",
            **extra,
        )

    def start(self) -> LocalRosCore:
        out = (self.log_dir / f"roscore-{self.port}.out").open("wb")
        self.proc = subprocess.Popen(
            ["roscore", "-p", str(self.port)],
            env=self.env(),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        deadline = time.monotonic() + self._timeout
        while not master_alive(self.uri, timeout_s=1.0):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"roscore on port {self.port} did not start (see {self.log_dir})")
            time.sleep(0.2)
        return self

    def stop(self, timeout_s: float = 10.0) -> None:
        if self.proc is not None:
            stop_process_group(self.proc, timeout_s)

    def __enter__(self) -> LocalRosCore:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process_group(
    proc: subprocess.Popen[bytes] | subprocess.Popen[str], timeout_s: float = 10.0
) -> None:
    """SIGTERM a child started with start_new_session (roscore's own children included), then SIGKILL."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
