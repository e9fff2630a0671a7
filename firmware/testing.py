"""Host-side helpers for testing the firmware: a killable MQTT broker process and the MicroPython runner.

The broker is the one place to switch from a plain amqtt broker to the project's secure broker
(`wsnav broker run`, in broker/) once it has landed: `BrokerProcess.start` is all the tests call.
Run as `python -m firmware.testing broker PORT` to serve a plain auth-less amqtt 0.12.1 broker on loopback.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

DEVICE = Path(__file__).resolve().parent / "device"
HOST_STUBS = Path(__file__).resolve().parent / "host_stubs"
HEAP = "38k"
"""The ESP8266's GC heap (DESIGN.md); on the 64-bit unix port objects are bigger, so this is conservative."""


def micropython_exe() -> str:
    """The unix-port `micropython` next to the running interpreter (the venv's), else on PATH."""
    here = Path(sys.executable).parent / "micropython"
    return str(here) if here.exists() else "micropython"


def micropython_env(build_dir: Path, pins_dir: Path | None = None) -> dict[str, str]:
    """Environment for the unix port: the built .mpy files (what goes on the board), then the fake
    machine/network modules, on MICROPYPATH. Source would not do: compiling app.py needs more than 38 KiB."""
    env = dict(os.environ)
    env["MICROPYPATH"] = f"{build_dir}:{HOST_STUBS}:.frozen"
    if pins_dir is not None:
        env["WSNAV_PINS"] = str(pins_dir)
    return env


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_port(host: str, port: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection((host, port), timeout=1.0):
                return True
        except OSError:
            time.sleep(0.1)
    return False


class BrokerProcess:
    """An MQTT broker in its own process on a fixed loopback port, so a test can kill -9 and restart it."""

    def __init__(self, port: int | None = None, log: Path | None = None) -> None:
        self.host = "127.0.0.1"
        self.port = port or free_port()
        self.log = log
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 60.0) -> None:
        cmd = [sys.executable, "-m", "firmware.testing", "broker", str(self.port)]
        out = open(self.log, "ab") if self.log else subprocess.DEVNULL  # noqa: SIM115
        root = Path(__file__).resolve().parent.parent
        self.proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, cwd=root)
        if not wait_port(self.host, self.port, timeout_s):
            self.kill()
            raise RuntimeError(f"broker did not listen on {self.host}:{self.port} within {timeout_s} s")

    def kill(self) -> None:
        """SIGKILL: no clean shutdown, no DISCONNECT to the clients, like a Raspberry Pi losing power."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)
        self.proc = None


def _serve_amqtt(port: int) -> None:
    from amqtt.broker import Broker

    config = {
        "listeners": {"default": {"type": "tcp", "bind": f"127.0.0.1:{port}"}},
        "plugins": {"amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}},
    }

    async def serve() -> None:
        broker = Broker(config)
        await broker.start()
        await asyncio.Event().wait()

    asyncio.run(serve())


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "broker":
        _serve_amqtt(int(sys.argv[2]))
    else:
        sys.exit("usage: python -m firmware.testing broker PORT")


def build_for_host(out: Path) -> tuple[Path, Path]:
    """Compile the firmware (as `wsnav firmware build` does) and the host stubs to .mpy under `out`.

    Returns (device_dir, stubs_dir) for MICROPYPATH. The stubs are compiled too: on the 38 KiB heap, compiling
    even a small source file at import time costs kilobytes the board never spends.
    """
    from firmware.build import build, mpy_cross_exe

    device = out / "device"
    stubs = out / "stubs"
    build(device)
    stubs.mkdir(parents=True, exist_ok=True)
    exe = mpy_cross_exe()
    for py in sorted(HOST_STUBS.glob("*.py")):
        subprocess.run([exe, "-o", str(stubs / (py.stem + ".mpy")), "-s", py.name, str(py)], check=True)
    return device, stubs


def micropython_cmd(module: str, *args: str) -> list[str]:
    """`micropython -X heapsize=38k -m MODULE ARGS...`: a host-stub driver module, run like the board."""
    return [micropython_exe(), "-X", f"heapsize={HEAP}", "-m", module, *args]


class NodeProcess:
    """A firmware driver running on the unix port, its stdout collected in a file the test can wait on."""

    def __init__(self, cmd: list[str], env: dict[str, str], log: Path) -> None:
        self.log = log
        self._out = open(log, "wb")  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, env=env, stdout=self._out, stderr=subprocess.STDOUT)

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
