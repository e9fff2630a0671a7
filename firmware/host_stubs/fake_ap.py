"""Test-only: the fake radio's access point settings (host_stubs/network.py's `WLAN(AP_IF).config`, called by
firmware/device/fallback_ap.py) written to `$WSNAV_PINS/ap` as one line "ESSID KEY AUTHMODE" for the test to read.
A module of its own so that only the access point's boot loads it: the node's heap in the tests pays nothing."""

import os


def configured(ap) -> None:
    with open((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/ap", "w") as f:
        f.write("%s %s %d" % (ap["essid"], ap["password"], ap["authmode"]))
