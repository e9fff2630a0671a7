"""The node has run healthy (app.Node.run: app._HEALTHY_MS without a loop error): loaded for that one call and
dropped, as command.py is for a command, and kept small so that it loads on a fragmented heap."""

import os


def settle(node) -> None:
    """The boot-loop count goes (otaboot.LOOPS) and an update on trial is confirmed (its state renamed `ota.ok`:
    otaboot.py removes the backups at the next boot; `info` says so at once, which `wsnav firmware ota` waits
    for), but only online with two states sent since the connect: until then the node calls this each pass."""
    if node.trial and (node.phase != 3 or node.sent < 2):  # 3: app._ONLINE
        return
    node.healthy_since = None
    try:
        os.remove("otaboot.loops")
    except OSError:
        pass  # no resets counted (the usual case)
    if node.trial:
        node.trial = False
        try:
            os.rename("ota.json", "ota.ok")
        except OSError:
            pass
        node.info_due_ms = node.ticks()
        print("ota: confirmed")
