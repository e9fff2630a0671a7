# Maintenance mode: run at the board's REPL by `wsnav firmware deploy` (firmware/deploy.py sends this file's
# text; it is never built or copied to the board, so it works on a fresh board and on any older firmware).
#
# On the ESP8266 a started machine.WDT cannot be stopped (no deinit; a soft reset does not undo it) and the
# SDK resets the board ~3.2 s after the last feed. Once mpremote's Ctrl-C has stopped the node's loop, nothing
# feeds it: this keeps feeding from a soft machine.Timer, whose callback the ESP8266 runs in any wait
# (mp_handle_pending while the REPL waits for input, between raw-REPL commands, during file writes), for as
# long as the host keeps asking. Every host command calls _wsnav_keep(), which extends the hold by
# _WSNAV_HOLD_MS; a host that goes away (cable pulled, laptop closed) stops extending it, feeding stops, and the
# watchdog resets the board into its application. Running this again replaces the previous timer.
# mpremote must not soft-reset while this runs (`resume`): a soft reset frees the timer's callback.
#
# Names start with _wsnav_: they live in the REPL's globals next to whatever main.py left there.
import binascii
import hashlib
import machine
import os
import time

_WSNAV_HOLD_MS = 300000

try:
    _wsnav_timer.deinit()  # noqa: F821  # pyright: ignore[reportUndefinedVariable] (a previous deploy's)
except NameError:
    pass
_wsnav_wdt = machine.WDT()  # the running one if the application started it, else started now
_wsnav_until = 0


def _wsnav_keep() -> None:
    """Hold maintenance for another _WSNAV_HOLD_MS from now."""
    global _wsnav_until
    _wsnav_until = time.ticks_add(time.ticks_ms(), _WSNAV_HOLD_MS)


def _wsnav_feed(_t) -> None:
    if time.ticks_diff(_wsnav_until, time.ticks_ms()) > 0:
        _wsnav_wdt.feed()


def _wsnav_sha(names) -> None:
    """Print "name sha256-hex" for each file ("name -" if it is missing), hashed in 256-byte pieces."""
    buf = bytearray(256)
    for name in names:
        h = hashlib.sha256()
        try:
            with open(name, "rb") as f:
                while True:
                    n = f.readinto(buf)
                    if not n:
                        break
                    h.update(memoryview(buf)[:n])
            print(name, binascii.hexlify(h.digest()).decode())
        except OSError:
            print(name, "-")


def _wsnav_rm(names) -> None:
    """Remove each file that exists."""
    for name in names:
        try:
            os.remove(name)
        except OSError:
            pass


_wsnav_keep()
_wsnav_feed(None)
_wsnav_timer = machine.Timer(-1)
_wsnav_timer.init(period=500, mode=machine.Timer.PERIODIC, callback=_wsnav_feed)
print("wsnav maintenance", _WSNAV_HOLD_MS)
