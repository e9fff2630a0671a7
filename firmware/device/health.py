"""The node has run healthy (app.Node.run: app._HEALTHY_S after boot, its last pass without an error): loaded
for that and dropped once done (it removes itself from sys.modules), as command.py is for a command, and kept
small so that it loads on a fragmented heap. Its names and strings are the firmware's already or longer than
10 characters: a new qstr of the loop can take a new qstr pool (diagnostics.py), which a connected node on the
tests' heap could not allocate."""

import os

from micropython import const

_OFFLINE_S = const(120)
"""A trial (an update's, a configuration's) that has not once been online this long after boot is rolled back:
a new Wi-Fi key or broker address that does not work, an app that never connects. Wi-Fi joins time out after
20 s and back off up to 60 s, so this is several tries."""


def apply(node) -> None:
    """The boot-loop count goes (otaboot.LOOPS) and an update on trial is confirmed (its state renamed `ota.ok`:
    otaboot.py removes the backups at the next boot; `info` says so at once, which `wsnav firmware ota` waits
    for), but only online with two states (heartbeats, changes) sent after the first connect's: until then the
    node calls this each pass, and a trial never online within _OFFLINE_S is ended (otaboot rolls it back at
    the reset). `node.trial` then says 0: done."""
    if node.trial == 2 and (node.phase != 3 or node.logic.publications < 3):  # 3: app._ONLINE
        if node.connects == 0 and node.uptime_s >= _OFFLINE_S:
            os.rename("ota.json", "ota.offline")  # the next boot rolls the trial back (otaboot.boot)
            print("ota: not online")
            __import__("machine").reset()
        return
    try:
        os.remove("otaboot.loops")
    except OSError:
        pass  # no resets counted (the usual case)
    if node.trial == 2:
        try:
            os.rename("ota.json", "ota.ok")
        except OSError:
            pass
        node.info_due_ms = node.ticks()
        print("ota: confirmed")
    node.trial = 0
    import sys

    sys.modules.pop("health", None)  # the app keeps no reference: the module's heap goes back
