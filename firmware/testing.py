"""Host-side helpers for testing the firmware: a killable MQTT broker process and the MicroPython runner.

The tests run the firmware against the project's own broker (`wsnav broker run`) with the node's real
credentials (`wsnav broker credentials`); `SiteBroker` is the one place that chooses and starts it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wsnav.broker.amqtt.embedded import BrokerProcess as EmbeddedBroker

DEVICE = Path(__file__).resolve().parent / "device"
HOST_STUBS = Path(__file__).resolve().parent / "host_stubs"
"""Test-only fakes and drivers for the unix port, beside device/ and never in it: never built or deployed."""


def host_stubs_of(checkout_firmware: Path) -> Path:
    """The host stubs of a checkout's firmware/ folder (before they left device/, they lived inside it)."""
    here = checkout_firmware / "host_stubs"
    return here if here.is_dir() else checkout_firmware / "device" / "host_stubs"


HEAP = "44k"
"""The 64-bit unix port's heap for the tests: at most the one that corresponds to the ESP8266's 38 KiB GC heap
(docs/architecture.md, "The ESP8266"), derived by bench.firmware_heap (`tests_heap`): main.py run to the node's
setup on both ports, the 32-bit WebAssembly port (the board's object sizes) at 38 KiB and this port; that is the
heap whose GC total is this port's used bytes plus the board's free bytes (measured 2026-11-28: PIR 36032 B used
here, 17504 B free on the board; HC-SR04 36544 and 17088: 54016 B). 40k was derived when the bench still counted
the port's uncollected garbage (4912 B free on the board); 44k since the fallback access point and the log ring
came in beside each other: at 40k the node could no longer build its first `info` ("info: no heap") and its
reconnect loop ran out of heap (tests/test_firmware_node.py, the DNS test, beside other tests), where the board
keeps 17 KB free. Still about 10 KB under the derived heap: the tests get less headroom than the board, never
more. Not twice 38 KiB:
bytecode and names are the same size on both ports and this port has more names in ROM; its Python stubs of
machine and network (4 KB, ROM on the board) are in the used bytes. The loop's objects are larger here (8-byte
pointers), so in the loop this is stricter than the board. bench.firmware_heap --quick (CI) fails when this is
more than the derived heap."""


def micropython_exe() -> str:
    """The unix-port `micropython` next to the running interpreter (the venv's), else on PATH."""
    here = Path(sys.executable).parent / "micropython"
    return str(here) if here.exists() else "micropython"


def micropython_env(device: Path, stubs: Path, pins_dir: Path | None = None) -> dict[str, str]:
    """Environment for the unix port: the built .mpy files (what goes on the board), then the compiled fake
    machine/network modules, on MICROPYPATH. Source would not do: compiling app.py needs more than 38 KiB."""
    env = dict(os.environ)
    env["MICROPYPATH"] = f"{device}:{stubs}"
    if pins_dir is not None:
        env["WSNAV_PINS"] = str(pins_dir)
    return env


SIMULATED_TIME = ("--node-publish-rate", "0")
"""`wsnav broker run` options for a driver on an accelerated clock (host_stubs/longrun.py): its node sends hours
of heartbeats in minutes, hundreds of messages a second, far over the broker's rate for a node (20/s; over it,
a QoS 1 publisher's connection is ended), as the simulator's embedded broker allows its simulated nodes."""


class SiteBroker:
    """The project's broker (`wsnav broker run`, broker/) for a site, as a process a test can kill -9 and
    restart on the same port with the same data folder. The one place that decides which broker the firmware
    tests talk to; `extra_args` are more `wsnav broker run` options (SIMULATED_TIME)."""

    def __init__(self, site: Path, credentials: Path, data: Path, extra_args: tuple[str, ...] = ()) -> None:
        self.site = site
        self.credentials = credentials
        self.data = data
        self.extra_args = extra_args
        self.host = "127.0.0.1"
        self.port = 0
        self._proc: EmbeddedBroker | None = None

    def start(self, timeout_s: float = 120.0) -> None:
        """Start (first time on a free port, then on the same port) and wait for its ready line."""
        from wsnav.broker.amqtt.embedded import BrokerProcess as EmbeddedBroker

        proc = EmbeddedBroker(
            self.site,
            self.credentials,
            host=self.host,
            port=self.port,
            data_dir=self.data,
            extra_args=list(self.extra_args),
            start_timeout_s=timeout_s,
        )
        self._proc = proc.start()
        self.port = proc.port

    def kill(self) -> None:
        """SIGKILL: no clean shutdown, no DISCONNECT to the clients, like a Raspberry Pi losing power."""
        if self._proc is not None:
            self._proc.kill()
        self._proc = None


FORMAT_FLASH = """
import os, sys
class Ram:
    def __init__(self, n): self.data = bytearray(n * 512)
    def readblocks(self, n, buf, off=0): buf[:] = self.data[n * 512 + off : n * 512 + off + len(buf)]
    def writeblocks(self, n, buf, off=0): self.data[n * 512 + (off or 0) : n * 512 + (off or 0) + len(buf)] = buf
    def ioctl(self, op, arg): return 64 if op == 4 else 512 if op == 5 else 0
bdev = Ram(64)
getattr(os, sys.argv[1]).mkfs(bdev)
with open(sys.argv[2], "wb") as f: f.write(bdev.data[:4096])
"""
FLASHBDEV = """class _Flash:
    def readblocks(self, n, buf, off=0):
        with open("flash.img", "rb") as f:
            f.seek(n * 4096 + off)
            f.readinto(buf)


bdev = _Flash()
"""


def fake_flash(fs: Path, vfs: str) -> None:
    """Give the board whose filesystem is the folder `fs` a flash chip holding a filesystem that MicroPython's
    own `os.<vfs>.mkfs` formatted (`VfsFat`: a board upgraded from before 1.13 without an erase; `VfsLfs2`: the
    default since): `flash.img` (its first 4 KiB) and a `flashbdev.py` reading it as the ESP8266 port's frozen
    module does (`bdev.readblocks`), for device/fscheck.py. The flash chip is the boundary faked here; the
    image is made by a separate unix-port process with room for the format, not on the board's heap."""
    cmd = [micropython_exe(), "-X", "heapsize=1m", "-c", FORMAT_FLASH, vfs, str(fs / "flash.img")]
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)
    (fs / "flashbdev.py").write_text(FLASHBDEV)


def write_credentials(site: Path, out: Path) -> None:
    """`wsnav broker credentials --site SITE --out OUT`, the command installers run."""
    cmd = [sys.executable, "-m", "wsnav.cli", "broker", "credentials", "--site", str(site), "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"broker credentials failed: {proc.stderr.strip()}")


def build_for_host(out: Path) -> tuple[Path, Path]:
    """Compile the firmware (as `wsnav firmware build` does) and the host stubs to .mpy under `out`.

    Returns (device_dir, stubs_dir) for MICROPYPATH. The stubs are compiled too: on the board's heap (HEAP), compiling
    even a small source file at import time costs kilobytes the board never spends.
    """
    from wsnav.firmware.build import build, mpy_cross_exe

    device = out / "device"
    stubs = out / "stubs"
    build(device)
    stubs.mkdir(parents=True, exist_ok=True)
    exe = mpy_cross_exe()
    for py in sorted(HOST_STUBS.glob("*.py")):
        subprocess.run([exe, "-o", str(stubs / (py.stem + ".mpy")), "-s", py.name, str(py)], check=True)
    return device, stubs


def versioned_sources(
    out: Path, version: str, append: dict[str, str] | None = None, consts: dict[str, int] | None = None
) -> Path:
    """A copy of firmware/device in `out` whose FIRMWARE_VERSION is `version` (what `info` reports, so an update's
    arrival shows), with text appended to modules named in `append` (e.g. an app.py that raises), and each
    `NAME = const(N)` named in `consts` given its value there (SHORT_TRIAL: a test's trial in seconds, not
    minutes; the board's build is never changed)."""
    import re

    out.mkdir(parents=True)
    for py in DEVICE.glob("*.py"):
        text = py.read_text()
        if py.name == "diagnostics.py":
            text = re.sub(r'^FIRMWARE_VERSION = ".*"$', f'FIRMWARE_VERSION = "{version}"', text, flags=re.M)
        for name, value in (consts or {}).items():
            text = re.sub(rf"^{name} = const\(\d+\)$", f"{name} = const({value})", text, flags=re.M)
        (out / py.name).write_text(text + (append or {}).get(py.name, ""))
    return out


SHORT_TRIAL = {"_HEALTHY_S": 8, "_OFFLINE_S": 30}
"""versioned_sources' `consts` for a quick trial: healthy 8 s after boot (app.py; the board: 30 s), rolled back
when not online 30 s after boot (health.py; the board: 120 s: room for a slow broker on a loaded machine, whose
CONNACK may take seconds, so that a good trial is never rolled back)."""


def parse_stats(output: str) -> dict[str, int]:
    """The "stat KEY VALUE KEY VALUE ..." lines a test driver prints (longrun, budget), as one dict."""
    stats: dict[str, int] = {}
    for line in output.splitlines():
        words = line.split()
        if words[:1] == ["stat"]:
            stats.update(zip(words[1::2], map(int, words[2::2]), strict=True))
    return stats


def micropython_cmd(module: str, *args: str) -> list[str]:
    """`micropython -X heapsize=HEAP -m MODULE ARGS...`: a host-stub driver module, run like the board."""
    return [micropython_exe(), "-X", f"heapsize={HEAP}", "-m", module, *args]


class NodeProcess:
    """A firmware driver running on the unix port, its stdout collected in a file the test can wait on."""

    def __init__(self, cmd: list[str], env: dict[str, str], log: Path, cwd: Path | None = None) -> None:
        self.log = log
        self._out = open(log, "wb")  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._out, stderr=subprocess.STDOUT, cwd=cwd)

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_output(self, text: str, timeout_s: float, count: int = 1) -> bool:
        """True once `text` appears `count` times in the output; False on timeout or if the process ended."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.output().count(text) >= count:
                return True
            if self.proc.poll() is not None:
                return self.output().count(text) >= count
            time.sleep(0.05)
        return False

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(timeout=30)
        self._out.close()
