"""The node has run healthy (app.Node.run: app._HEALTHY_S after boot, its last pass without an error): loaded
for that and dropped once done (it removes itself from sys.modules), as command.py is for a command, and kept
small so that it loads on a fragmented heap."""

import os


def apply(node) -> None:
    """The boot-loop count goes (otaboot.LOOPS) and an update on trial is confirmed (its state renamed `ota.ok`:
    otaboot.py removes the backups at the next boot; `info` says so at once, which `wsnav firmware ota` waits
    for), but only online with two states (heartbeats, changes) sent after the first connect's: until then the
    node calls this each pass. `node.trial` then says 0: done."""
    if node.trial == 2 and (node.phase != 3 or node.logic.publications < 3):  # 3: app._ONLINE
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
