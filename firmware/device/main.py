# Runs after boot.py; kept as source because the board runs main.py by name. The node itself is app.mpy.
# The config is read before the rest of the firmware is imported, and its parser is then dropped, so the
# JSON parsing and the checks never compete with the MQTT client for the 38 KiB heap. Then otaboot (dropped
# too) counts this boot in a pending over-the-air update: in update mode it runs the updater and never returns;
# a failing trial is rolled back. If the app cannot be imported or set up: rollback, or safe mode (connected,
# watchdog fed, waiting for an update), never the REPL.
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
    import otaboot

    otaboot.boot(cfg)
    del otaboot
    del sys.modules["otaboot"]
    gc.collect()
    try:
        import app

        app.main(cfg)
    except Exception as exc:
        import otaboot

        otaboot.failed(cfg, exc)
