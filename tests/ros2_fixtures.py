"""Shared by the ROS 2 bridge's tests: the DDS peers run as processes beside the bridge (tests/dds_peer.py and the
native Cyclone 0.10 / Fast DDS 2.9 programs), the topics and QoS they expect, and the grid the ROS 1 bridge serves."""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from tests.conftest import REPO, require_tool
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_grid import ZoneGridCodec
from wsnav.schemas.site import Site

GRID = "rt/wsn/zone_grid"
INFO = "rt/wsn/costmap_filter_info"
COSTMAP_FILTER_INFO_MSG = """\
std_msgs/Header header
uint8 type
string filter_mask_topic
float32 base
float32 multiplier
"""
"""nav2_msgs/msg/CostmapFilterInfo.msg in Nav2's humble branch, comments left out."""
LATCHED = {
    "reliability": "RELIABLE",
    "durability": "TRANSIENT_LOCAL",
    "history": ["KEEP_LAST", 1],
    "data_representation": ["XCDR1"],
}
"""What the matched writer must announce: Nav2's map QoS, in the one representation Humble's rmw accepts."""


def typestore() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(COSTMAP_FILTER_INFO_MSG, "nav2_msgs/msg/CostmapFilterInfo"))
    return store


def domain_id() -> int:
    """A domain of this test run's own, so no other DDS traffic on the machine mixes in."""
    return 100 + os.getpid() % 100


class NativePeer:
    """A peer program as a child process printing JSON lines: `{"ready": true}`, then one line per sample, kept
    in `samples` as they arrive; its stderr goes to a file (a crash's last words, without a pipe to fill)."""

    def __init__(
        self, name: str, argv: list[str], env: dict[str, str] | None = None, *, commands: bool = False
    ) -> None:
        """`commands`: its stdin is a pipe the test writes to (`command`)."""
        self.name = name
        self.samples: list[dict[str, Any]] = []
        self._err = tempfile.TemporaryFile("w+")  # noqa: SIM115  # lives as long as the peer; closed by the GC
        self.proc = subprocess.Popen(
            argv,
            cwd=REPO,
            stdin=subprocess.PIPE if commands else None,
            stdout=subprocess.PIPE,
            stderr=self._err,
            text=True,
            env=env,
            start_new_session=True,
        )
        self._ready = threading.Event()
        self._pump = threading.Thread(target=self._read, daemon=True)
        self._pump.start()
        if not self._ready.wait(30):
            self.stop()
            pytest.fail(f"the {name} peer did not start: {self.stderr()}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            item = json.loads(line)
            if item.get("ready"):
                self._ready.set()
            else:
                self.samples.append(item)

    def command(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def stderr(self) -> str:
        self._err.seek(0)
        return self._err.read()[-2000:]

    def stop(self) -> int:
        """SIGTERM, then the exit code (-11: it had died of SIGSEGV)."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            code = self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait(10)
        self._pump.join(5)
        return code


class DdsPeer(NativePeer):
    """tests/dds_peer.py (Cyclone 11 in Python) as a child process; its samples as they arrive."""

    def __init__(self, domain: int, *names: str, gid_bytes: int = 24) -> None:
        argv = [
            sys.executable,
            "-m",
            "tests.dds_peer",
            "--domain",
            str(domain),
            "--gid-bytes",
            str(gid_bytes),
        ]
        super().__init__("Cyclone 11 (tests/dds_peer.py)", [*argv, *names])

    def of(self, topic: str) -> list[dict[str, Any]]:
        return [s for s in list(self.samples) if s["topic"] == topic]


def decode(store: Any, sample: dict[str, Any], msgtype: str) -> Any:
    return store.deserialize_cdr(base64.b64decode(sample["cdr"]), msgtype)


def expected_grid(codec: ZoneGridCodec, feed: ZoneFeed) -> NDArray[np.int8]:
    """What `wsnav ros bridge` (ROS 1) serves for these zone states: ZoneBridgeNode.full_grid_message's data."""
    return codec.encode(feed.costs).ravel()


def bridge_args(site: Site, broker: str, credentials: Path, domain: int) -> list[str]:
    return [
        "ros2", "bridge", "--site", str(site.path), "--broker", broker, "--credentials", str(credentials),
        "--domain", str(domain), "--log-level", "info",
    ]  # fmt: skip


HEADERS = {
    "cyclonedds-dev": Path("/usr/include/dds/dds.h"),
    "libfastrtps-dev": Path("/usr/include/fastdds/dds/domain/DomainParticipant.hpp"),
}
ROS_ENV = ("ROS_LOCALHOST_ONLY", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "CYCLONEDDS_URI")


def require_header(package: str) -> None:
    """A Debian -dev package's header: skip without it, fail under WSNAV_REQUIRE_TOOLS=1 (CI)."""
    if not HEADERS[package].exists():
        if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
            pytest.fail(f"{HEADERS[package]} missing: apt-get install {package} (WSNAV_REQUIRE_TOOLS=1)")
        pytest.skip(f"{package} not installed")


def clean_env() -> dict[str, str]:
    """This process's environment without ROS 2's discovery variables or a Cyclone config of the caller's."""
    return {k: v for k, v in os.environ.items() if k not in ROS_ENV}


SOURCES = REPO / "tests" / "dds_peers"


def build(out: Path) -> None:
    """The peers from tests/dds_peers: idlc's C for the grid type with and without type information, gcc, g++."""
    idlc, gcc, gxx = require_tool("idlc"), require_tool("gcc"), require_tool("g++")
    for variant, flags in (("typeinfo", []), ("no_typeinfo", ["-t"])):
        gen = out / variant
        gen.mkdir()
        subprocess.run([idlc, *flags, "-o", str(gen), str(SOURCES / "ros2_grid.idl")], check=True)
        subprocess.run(
            [gcc, "-O1", "-o", str(out / f"cyclone_peer_{variant}"), f"-I{gen}",
             str(SOURCES / "cyclone_peer.c"), str(gen / "ros2_grid.c"), "-lddsc"],
            check=True,
        )  # fmt: skip
    subprocess.run(
        [gxx, "-O0", "-o", str(out / "fastdds_peer"), str(SOURCES / "fastdds_peer.cpp"), "-lfastrtps", "-lfastcdr"],
        check=True,
    )  # fmt: skip


@pytest.fixture(scope="session")
def peer_binaries() -> Path:
    """The compiled peers, cached in the temp dir by the sources' hash (the Fast DDS one takes seconds of g++)."""
    require_header("cyclonedds-dev")
    require_header("libfastrtps-dev")
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sorted(SOURCES.iterdir()))).hexdigest()[:16]
    out = Path(tempfile.gettempdir()) / f"wsnav-dds-peers-{digest}"
    if not (out / "fastdds_peer").exists():
        work = Path(tempfile.mkdtemp(prefix="wsnav-dds-peers-build-"))
        try:
            build(work)
            with contextlib.suppress(OSError):  # another run built it meanwhile
                work.rename(out)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return out


NAV2_SOURCES = [SOURCES / "nav2_action.idl", SOURCES / "nav2_action_server.c"]


@pytest.fixture(scope="session")
def nav2_server() -> Path:
    """The stand-in, built once per source version (idlc -t: no type information, as rmw_cyclonedds)."""
    require_header("cyclonedds-dev")
    idlc, gcc = require_tool("idlc"), require_tool("gcc")
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in NAV2_SOURCES)).hexdigest()[:16]
    out = Path(tempfile.gettempdir()) / f"wsnav-nav2-server-{digest}"
    if not (out / "nav2_action_server").exists():
        work = Path(tempfile.mkdtemp(prefix="wsnav-nav2-server-build-"))
        try:
            subprocess.run([idlc, "-t", "-o", str(work), str(NAV2_SOURCES[0])], check=True)
            subprocess.run(
                [gcc, "-O1", "-o", str(work / "nav2_action_server"), f"-I{work}", str(NAV2_SOURCES[1]),
                 str(work / "nav2_action.c"), "-lddsc", "-lm"],
                check=True,
            )  # fmt: skip
            with contextlib.suppress(OSError):  # another run built it meanwhile
                work.rename(out)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return out / "nav2_action_server"


NAV2_FASTDDS_SOURCE = SOURCES / "nav2_fastdds_server.cpp"


@pytest.fixture(scope="session")
def nav2_fastdds_server() -> Path:
    """The Fast DDS 2.9 stand-in (rmw_fastrtps's service layout), built once per source version."""
    require_header("libfastrtps-dev")
    gxx = require_tool("g++")
    digest = hashlib.sha256(NAV2_FASTDDS_SOURCE.read_bytes()).hexdigest()[:16]
    out = Path(tempfile.gettempdir()) / f"wsnav-nav2-fastdds-server-{digest}"
    if not (out / "nav2_fastdds_server").exists():
        work = Path(tempfile.mkdtemp(prefix="wsnav-nav2-fastdds-server-build-"))
        try:
            subprocess.run(
                [gxx, "-O0", "-o", str(work / "nav2_fastdds_server"), str(NAV2_FASTDDS_SOURCE),
                 "-lfastrtps", "-lfastcdr"],
                check=True,
            )  # fmt: skip
            with contextlib.suppress(OSError):  # another run built it meanwhile
                work.rename(out)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return out / "nav2_fastdds_server"
