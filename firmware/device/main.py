# Runs after boot.py; kept as source because the board runs main.py by name. The node itself is app.mpy.
# The config is read before the rest of the firmware is imported, and its parser is then dropped, so the
# JSON parsing and the checks never compete with the MQTT client for the 38 KiB heap.
import gc
import sys

import nodeconfig

try:
    cfg = nodeconfig.load("config.json")
except nodeconfig.ConfigError as exc:
    print(exc)  # stays at the REPL, watchdog not started: fix config.json with mpremote
    cfg = None
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
if cfg is not None:
    import app

    app.main(cfg)
