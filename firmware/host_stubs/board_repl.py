"""Test driver: an ESP8266's boot and REPL on the unix port, for firmware/unix_board.py (run with cwd = the board's
filesystem, which is also first on MICROPYPATH).

    micropython -X heapsize=96k -m board_repl   (unix_board.py says why not the board's heap)

As the board does after a reset: run boot.py, then main.py (a Ctrl-C, SIGINT here, stops it with
KeyboardInterrupt), then wait at the REPL. The REPL speaks the shape of mpremote's raw REPL on stdin/stdout:
it prints the prompt "\\x05raw>" and reads code up to "\\x04", runs it in the globals main.py ran in, and
answers with the printed output, "\\x04", the exception if any, "\\x04". While it waits for input it runs the
soft timers, as the ESP8266 does (mp_hal_stdin_rx_chr -> mp_event_handle_nowait -> mp_handle_pending).
machine.WDT reports to the host's watchdog (PipeWDT); the fake radio has its access point (fake_ap.py).
"""

import os
import sys

import fake_ap
import machine
import select
import soft_timers


class PipeWDT:
    """machine.WDT reporting its start ("s") and each feed ("f") down the pipe $WSNAV_WDT to the host's
    watchdog. As on the ESP8266 it has no deinit, and creating it again returns the running one."""

    out = None

    def __init__(self, id=0, timeout=5000):
        if PipeWDT.out is None:
            PipeWDT.out = open(os.getenv("WSNAV_WDT") or "/dev/null", "wb")
            self._say(b"s")

    def _say(self, what):
        out = PipeWDT.out
        if out is not None:
            out.write(what)  # unbuffered (and flush() would fsync, which a pipe refuses)

    def feed(self):
        self._say(b"f")


machine.WDT = PipeWDT  # pyright: ignore[reportAttributeAccessIssue]
soft_timers.install()
fake_ap.install()  # the fallback access point's side of the fake radio
env = {"__name__": "__main__"}
stdin = getattr(sys.stdin, "buffer", None)
"""The raw bytes of stdin; None on MicroPython 1.19, whose sys.stdin (a TextIOWrapper) has no `buffer`: then
its text is read and encoded (what the host sends is ASCII: code and Ctrl characters)."""
poller = select.poll()
poller.register(sys.stdin, select.POLLIN)


def run_file(name):
    try:
        with open(name) as f:
            code = f.read()
    except OSError:
        return
    try:
        exec(code, env)
    except Exception as exc:
        sys.print_exception(exc)


try:  # a Ctrl-C anywhere in boot.py or main.py leaves the board at its REPL
    print("\x06boot")
    run_file("boot.py")
    run_file("main.py")
except KeyboardInterrupt:
    print("KeyboardInterrupt")
while True:
    try:
        print("\x05raw>")
        code = b""
        while not code.endswith(b"\x04"):
            if poller.poll(20):
                c = stdin.read(1) if stdin is not None else sys.stdin.read(1).encode()
                if not c:
                    raise SystemExit(0)  # the host closed the line
                code += c
            else:
                soft_timers._run_timers()
        error = ""
        try:
            exec(code[:-1], env)
        except Exception as exc:
            error = "%s: %s" % (type(exc).__name__, exc)
        print("\x04" + error + "\x04")
    except KeyboardInterrupt:
        pass
