"""The serial link to a board, as `wsnav firmware deploy` uses it: run code at its REPL, copy a file, reset.

`Board` is the interface the deploy logic (firmware/deploy.py) talks to; `MpremoteBoard` is the real one, one
`mpremote` session per call. Every session starts with `resume`: without it mpremote soft-resets the board on
connecting, which would free the maintenance timer's callback while its timer still runs (the ESP8266's
soft_reset does not stop machine.Timer) and would not stop the watchdog either. The tests drive the same deploy
logic through `firmware.unix_board.UnixBoard`, the MicroPython unix port behind the same three calls.
"""

from __future__ import annotations

import shlex
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

from wsnav.firmware.build import tool_path


class BoardError(Exception):
    """The board did not do what was asked (an exception at its REPL, a lost link); one line."""


class Board(Protocol):
    def run(self, code: str) -> str:
        """Run `code` at the board's REPL (stopping whatever runs there, as Ctrl-C does); what it printed.
        Raises BoardError with the exception's last line if the code raised."""
        ...

    def put(self, local: Path, remote: str) -> None:
        """Copy a host file to the board's filesystem as `remote`."""
        ...

    def reset(self) -> None:
        """Hard reset (machine.reset()); returns without waiting for the board to boot."""
        ...

    def console(self, timeout_s: float) -> Iterator[str]:
        """The lines the board prints on its serial console from now on (after a reset: its boot, then the
        node's own messages), until `timeout_s` has passed; the caller stops reading when it has seen enough."""
        ...


class MpremoteBoard:
    """A board on a serial port, through mpremote (the one MicroPython ships)."""

    def __init__(self, port: str, timeout_s: float = 120.0) -> None:
        self.port = port
        self.timeout_s = timeout_s
        self.mpremote = tool_path("mpremote")

    def command(self, *args: str) -> list[str]:
        """`mpremote connect PORT resume ARGS...`: the command line of one session."""
        return [self.mpremote, "connect", self.port, "resume", *args]

    def _session(self, *args: str) -> str:
        cmd = self.command(*args)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=self.timeout_s, check=False)
        except OSError as exc:
            raise BoardError(f"cannot run {cmd[0]}: {exc.strerror}") from None
        except subprocess.TimeoutExpired:
            raise BoardError(
                f"mpremote gave no answer within {self.timeout_s:.0f} s on {self.port}"
            ) from None
        if proc.returncode != 0:
            lines = (proc.stderr.strip() or proc.stdout.strip() or "no message").splitlines()
            raise BoardError(f"{shlex.join(cmd[4:6])}: {lines[-1]}")
        return proc.stdout

    def run(self, code: str) -> str:
        return self._session("exec", code)

    def put(self, local: Path, remote: str) -> None:
        self._session("fs", "cp", str(local), ":" + remote)

    def reset(self) -> None:
        self._session("reset")

    def console(self, timeout_s: float) -> Iterator[str]:
        import serial  # pyserial: mpremote's own dependency

        link = serial.Serial()
        link.port = self.port
        link.baudrate = 115200
        link.timeout = 0.5
        link.dtr = link.rts = (
            False  # a NodeMCU's auto-reset circuit: opening the port must not reset the board
        )
        try:
            link.open()
        except serial.SerialException as exc:
            raise BoardError(f"cannot open {self.port}: {exc}") from None
        deadline = time.monotonic() + timeout_s
        with link:
            while time.monotonic() < deadline:
                raw = link.readline()
                if raw:
                    yield raw.decode(errors="replace").rstrip("\r\n")
