"""An ESP8266 zone node as `wsnav firmware deploy` sees it over USB, played by the MicroPython unix port: the
test side of `firmware.board.Board` (the fake is only the serial line; the firmware, main.py, the maintenance
code and the file operations are the real ones, run by MicroPython).

- Its filesystem is a host folder; a boot runs boot.py then main.py in it (`host_stubs/board_repl.py`).
- Ctrl-C is SIGINT; the REPL answers raw-REPL-shaped commands on stdin/stdout at 115200 baud, one Ctrl-C per
  session as mpremote sends; a file goes in 256-byte write commands, as mpremote's `fs cp` sends it.
- `serve_pty()` also puts it on a pseudo-terminal that speaks MicroPython's raw REPL (Ctrl-C, Ctrl-A, commands
  ended by Ctrl-D answered "OK", output, Ctrl-D, error, Ctrl-D, ">"; raw-paste mode declined; Ctrl-D alone a
  soft reset, which stops soft timers but not the watchdog), so the real mpremote, and
  `firmware.board.MpremoteBoard`, can talk to it.
- Its watchdog behaves as the ESP8266's: started by the first machine.WDT(), it cannot be stopped (no deinit,
  nothing the board runs undoes it), and `WDT_TIMEOUT_S` after the last feed it resets the board (the process
  is killed and started again). machine.reset() restarts it too. `resets` records each cause, and the next
  boot's machine.reset_cause() reports it as the ESP8266 would.
"""

from __future__ import annotations

import contextlib
import os
import pty
import signal
import subprocess
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

from wsnav.firmware.board import BoardError
from wsnav.firmware.testing import micropython_env, micropython_exe

WDT_TIMEOUT_S = 3.2
"""The ESP8266 SDK's software watchdog: a reset about 3.2 s after the last feed."""
BAUD = 115200
"""The ESP8266's REPL UART: what the host sends takes its time on the wire (10 bits a byte), so a deploy lasts
as long as it does over USB (seconds: longer than the watchdog)."""
SESSION_S = 0.2
"""What starting an mpremote session costs before the first command (port open, Ctrl-C, raw REPL)."""
PROMPT = b"\x05raw>\n"
SOFT_RESET = b"""import soft_timers
soft_timers._timers.clear()
g = globals()
g.clear()
g["__name__"] = "__main__"
"""
"""What an ESP8266's soft reset does to a running maintenance mode: the heap is swept (the REPL's globals, the
timer's callback) and soft timers stop, while the watchdog goes on (main.c's soft_reset; machine_wdt.c)."""
CHUNK = 256
"""Bytes per write command, as mpremote's fs cp sends them."""


class _Boot:
    """One run of the board, from a reset to the next: the process, its serial output and its watchdog."""

    def __init__(self, cmd: list[str], env: dict[str, str], fs: Path, log: Path) -> None:
        rfd, wfd = os.pipe()
        env = dict(env, WSNAV_WDT=f"/dev/fd/{wfd}")
        self.proc = subprocess.Popen(
            cmd,
            cwd=fs,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            pass_fds=(wfd,),
        )
        os.close(wfd)
        self.out = bytearray()
        self.cond = threading.Condition()
        self.wdt_started = False
        self.last_feed = time.monotonic()
        self.killed_by_wdt = False
        self._log = log.open("ab")
        self._reader = threading.Thread(target=self._read_serial, daemon=True)
        self._reader.start()
        threading.Thread(target=self._read_wdt, args=(rfd,), daemon=True).start()

    def _read_serial(self) -> None:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        while chunk := os.read(fd, 4096):
            self._log.write(chunk)
            self._log.flush()
            with self.cond:
                self.out += chunk
                self.cond.notify_all()
        with self.cond:
            self.cond.notify_all()

    def _read_wdt(self, rfd: int) -> None:
        with os.fdopen(rfd, "rb", buffering=0) as pipe:
            while data := pipe.read(4096):
                with self.cond:
                    self.wdt_started = self.wdt_started or b"s" in data
                    self.last_feed = time.monotonic()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def wait_for(self, text: bytes, start: int, timeout_s: float) -> int:
        """The position just after `text` in the output from `start` on; BoardError if the board reset first."""
        deadline = time.monotonic() + timeout_s
        with self.cond:
            while True:
                i = self.out.find(text, start)
                if i >= 0:
                    return i + len(text)
                if not self.alive():
                    raise BoardError("the board reset")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise BoardError(f"no {text!r} from the board within {timeout_s} s")
                self.cond.wait(min(left, 0.1))

    def send(self, data: bytes) -> None:
        assert self.proc.stdin is not None
        time.sleep(len(data) * 10 / BAUD)
        try:
            self.proc.stdin.write(data)
            self.proc.stdin.flush()
        except (BrokenPipeError, ValueError):
            raise BoardError("the board reset") from None

    def stop(self) -> None:
        if self.alive():
            self.proc.kill()
        self.proc.wait(timeout=30)
        # The last output read and logged (the reader ends at the pipe's end), then the log closes: closed first,
        # a late write raised in the reader ("write to closed file").
        self._reader.join(5)
        self._log.close()


class UnixBoard:
    """A board on the unix port; `power_on()` first, `close()` at the end."""

    def __init__(self, fs: Path, stubs: Path, log: Path, pins: Path) -> None:
        self.fs = fs
        self.log = log
        # A larger heap than the board's 38 KiB: this driver's REPL is Python, the board's is C (the node's heap is
        # measured by tests/test_firmware_node.py and bench/firmware_heap.py, not here).
        self.cmd = [micropython_exe(), "-X", "heapsize=96k", "-m", "board_repl"]
        self.env = micropython_env(fs, stubs, pins)
        self.pins = pins
        self.resets: list[str] = []
        self._boot: _Boot | None = None
        self._lock = threading.RLock()
        self._closed = threading.Event()
        self._monitor = threading.Thread(target=self._supervise, daemon=True)
        self._pty: tuple[int, int] | None = None

    # -- the hardware: power, reset, watchdog ------------------------------------------------------------
    def power_on(self) -> None:
        self._start()
        self._monitor.start()

    def _start(self) -> None:
        with self._lock:
            self._boot = _Boot(self.cmd, self.env, self.fs, self.log)
            self._boot.wait_for(b"\x06boot\n", 0, 60)

    def _supervise(self) -> None:
        while not self._closed.wait(0.02):
            with self._lock:
                boot = self._boot
                if boot is None:
                    continue
                if boot.alive():
                    with boot.cond:
                        starved = boot.wdt_started and time.monotonic() - boot.last_feed > WDT_TIMEOUT_S
                    if not starved:
                        continue
                    boot.killed_by_wdt = True
                    boot.proc.kill()
                    boot.proc.wait()
                code = boot.proc.returncode
                self.resets.append(
                    "watchdog" if boot.killed_by_wdt else "reset" if code == 75 else f"exit {code}"
                )
                # What machine.reset_cause() says at the next boot (host_stubs/machine.py): the ESP8266's rst_info
                # reason, 1 after its watchdog, 4 after machine.reset(), 0 (power on) after a power cut.
                cause = 1 if boot.killed_by_wdt else 4 if code == 75 else 0
                (self.pins / "reset_cause").write_text(str(cause))
                boot.stop()
                self._start()

    def boots(self) -> int:
        return len(self.resets) + 1

    def wdt_fed_within(self, seconds: float) -> bool:
        """True if the running board started its watchdog and fed it in the last `seconds`."""
        boot = self._boot
        if boot is None:
            return False
        with boot.cond:
            return boot.wdt_started and time.monotonic() - boot.last_feed < seconds

    def close(self) -> None:
        self._closed.set()
        if self._monitor.is_alive():
            self._monitor.join(5)
        with self._lock:
            if self._boot is not None:
                self._boot.stop()
        if self._pty is not None:
            for fd in self._pty:
                os.close(fd)

    # -- the serial line: what mpremote does ------------------------------------------------------------
    def _session(self) -> _Boot:
        """Ctrl-C, then wait for the REPL's prompt: the start of every mpremote session (which also takes its
        time to open the port and enter the raw REPL)."""
        time.sleep(SESSION_S)
        with self._lock:
            boot = self._boot
        if boot is None or not boot.alive():
            raise BoardError("the board is not running")
        mark = len(boot.out)
        boot.proc.send_signal(signal.SIGINT)
        boot.wait_for(PROMPT, mark, 30)
        return boot

    def _exec(self, boot: _Boot, code: str) -> str:
        mark = len(boot.out)
        boot.send(code.encode() + b"\x04")
        end_out = boot.wait_for(b"\x04", mark, 60)
        end_err = boot.wait_for(b"\x04", end_out, 60)
        output = bytes(boot.out[mark : end_out - 1]).decode(errors="replace")
        error = bytes(boot.out[end_out : end_err - 1]).decode(errors="replace").strip()
        if error:
            raise BoardError(error)
        boot.wait_for(PROMPT, end_err, 30)
        return output

    def interrupt(self) -> None:
        """Ctrl-C alone, as a person at the serial console would press it."""
        self._session()

    def run(self, code: str) -> str:
        boot = self._session()
        return self._exec(boot, code)

    def put(self, local: Path, remote: str) -> None:
        data = local.read_bytes()
        boot = self._session()
        self._exec(boot, f"f=open({remote!r},'wb')\nw=f.write")
        for i in range(0, len(data), CHUNK):
            self._exec(boot, f"w({data[i : i + CHUNK]!r})")
        self._exec(boot, "f.close()")

    def reset(self) -> None:
        boot = self._session()
        boot.send(b"import machine\nmachine.reset()\x04")

    def console(self, timeout_s: float) -> Iterator[str]:
        """What the board prints from now on, across resets (each boot's output follows the last's)."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            boot, start = self._boot, len(self._boot.out) if self._boot else 0
        pending = b""
        while time.monotonic() < deadline:
            with self._lock:
                if self._boot is not boot:
                    boot, start = self._boot, 0
            if boot is None:
                time.sleep(0.05)
                continue
            with boot.cond:
                if len(boot.out) == start and boot.alive():
                    boot.cond.wait(min(0.1, max(0.0, deadline - time.monotonic())))
                chunk = bytes(boot.out[start:])
            start += len(chunk)
            if not chunk and not boot.alive():
                time.sleep(0.05)  # reset: the supervisor starts the next boot
            pending += chunk
            *lines, pending = pending.split(b"\n")
            for line in lines:
                yield line.decode(errors="replace").rstrip("\r")

    # -- the same board behind a pseudo-terminal, for mpremote --------------------------------------------
    def serve_pty(self) -> str:
        """The path of a pseudo-terminal where this board answers as an ESP8266's raw REPL does."""
        master, slave = pty.openpty()
        tty.setraw(slave)
        self._pty = (master, slave)  # the slave stays open: the terminal outlives each mpremote session
        threading.Thread(target=self._serve, args=(master,), daemon=True).start()
        return os.ttyname(slave)

    def _serve(self, master: int) -> None:
        raw = False
        code = bytearray()
        while not self._closed.is_set():
            try:
                data = os.read(master, 4096)
            except OSError:
                return
            try:
                for b in data:
                    if b == 0x03:  # Ctrl-C: interrupt whatever runs
                        code.clear()
                        with contextlib.suppress(BoardError):
                            self._session()
                    elif b == 0x01:  # Ctrl-A: raw REPL
                        raw = True
                        code.clear()
                        os.write(master, b"raw REPL; CTRL-B to exit\r\n>")
                    elif b == 0x02:  # Ctrl-B: back to the friendly REPL
                        raw = False
                        os.write(master, b"\r\n>>> ")
                    elif raw and b == 0x04 and not code:  # Ctrl-D on an empty command: soft reset
                        os.write(master, b"OK\r\nMPY: soft reboot\r\n")
                        self._serve_command(SOFT_RESET)
                        os.write(master, b"raw REPL; CTRL-B to exit\r\n>")
                    elif raw and b == 0x04:  # Ctrl-D: run the command
                        os.write(master, b"OK")
                        os.write(master, self._serve_command(bytes(code)))
                        code.clear()
                    elif raw:
                        code.append(b)
                        if code.endswith(b"\x05A\x01"):  # raw-paste mode: understood, not supported
                            del code[-3:]
                            os.write(master, b"R\x00")
            except OSError:  # the pty was closed (the board shut down) while a command ran
                return

    def _serve_command(self, code: bytes) -> bytes:
        boot = self._boot
        if boot is None:
            return b"\x04board not running\x04>"
        mark = len(boot.out)
        try:
            boot.send(code + b"\x04")
            end_out = boot.wait_for(b"\x04", mark, 600)
            end_err = boot.wait_for(b"\x04", end_out, 60)
            boot.wait_for(PROMPT, end_err, 30)
        except BoardError:
            return b""  # it reset (machine.reset(), the watchdog): mpremote has had its "OK" and left
        return bytes(boot.out[mark:end_err]) + b">"
