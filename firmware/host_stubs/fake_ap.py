"""Test-only: the fake radio's access point (firmware/device/fallback_ap.py), installed by board_repl (the boards
of the OTA and access point tests) and bench.firmware_heap's run, not by host_stubs/network.py: the node's own
tests run at the tests' heap (testing.HEAP), where even 192 B more of stub cost a command its heap.

`WLAN(AP_IF).config(essid=, password=, authmode=)` writes "ESSID KEY AUTHMODE" to `$WSNAV_PINS/ap` for the test to
read; `network.AP_PORT` is $WSNAV_AP_PORT (the board serves port 80). What it leaves out: the access point is not a
radio here but the host, so there is no WPA2 and no association; whoever reaches the port is "in"."""

import os

import network

_plain = network.WLAN.config


def _config(self, what=None, pm=2, **ap):
    if not ap:
        return _plain(self, what, pm)  # pyright: ignore[reportCallIssue] (the stub's config, not the board's)
    with open((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/ap", "w") as f:
        f.write("%s %s %d" % (ap["essid"], ap["password"], ap["authmode"]))


def install() -> None:
    network.WLAN.config = _config  # pyright: ignore[reportAttributeAccessIssue]
    network.AP_PORT = int(os.getenv("WSNAV_AP_PORT") or 80)  # pyright: ignore[reportAttributeAccessIssue]
