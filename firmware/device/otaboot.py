"""The boot's side of an over-the-air update (OTA): what main.py decides before it imports the app.

`ota.json` holds an update's state across resets (every write goes to `ota.jtmp` first, then a rename: a power
cut leaves the old state or the new one, never half of one):
- `fetch`: command.py wrote it (an `update` command); boot into update mode (updater.py: nothing else loaded);
  `config` likewise (a `config` command): update mode fetches a configuration (otaconfig.py), whose one file
  `config.json` then goes through `swap` and `trial` as an update's files do; so does one posted to the fallback
  access point (fallback_ap.py, started here when app.py left its marker `wifi.fallback`; a trial then pending
  is rolled back first: its network did not join);
- `swap`: every new file is whole in `<name>.tmp` and hash-checked; `swap` renames them in (idempotent; here,
  not in the updater, which may be one of the files a power cut left half moved);
- `trial`: the new files are in, the old ones kept as `<name>.bak`; the app confirms the update once it has
  run healthy for a while, connected (health.apply renames the state `ota.ok`; the next boot removes the
  backups). A trial that boots MAX_BOOTS times without confirming (a reset before connecting, a loop that fails
  later and starves the watchdog), that is not online within its bound (health.py), or whose
  `import app` fails, is rolled back (`rollback`).
Every boot with a state counts one in it: an update mode that keeps resetting (no broker, no operator tool)
is abandoned after MAX_BOOTS and the old app runs. The app confirms a trial only once it has run healthy for a
while (health.apply: connected, states sent, no loop error), so a version that fails later is rolled back too.

Outside an update, a boot after a watchdog or exception reset counts one in `LOOPS`; the app clears it once
healthy. At MAX_BOOTS such resets in a row the app is not started: safe mode (connected, waiting for an update);
its own reset after safemode.SAFE_MS tries the app once more. A power-on or reset-pin boot (a person) clears it. Never replaced by an update (schemas OTA_BOOT_FILES): the
rollback must work whatever the update brought. Loaded at boot and dropped before the app is imported.
"""

import json
import os

STATE = "ota.json"
MAX_BOOTS = 3
# Two more files, named in place and longer than 10 characters, so neither is a new qstr of every boot (as LOOPS;
# diagnostics.py says why that counts): "ota.offline", the state renamed by health.py when a trial was not online
# within its bound (the next boot rolls it back); "config.rolled", a configuration was rolled back (the next
# boot's app says so in its first `info`; lost if that boot never gets online: the old configuration did before).
LOOPS = "otaboot.loops"
"""Watchdog or exception resets in a row, outside an update (health.apply removes it)."""
APP_ONLY = (
    "app payloads debounce node_logic backoff sensing diagnostics digital_sensor ultrasonic command health"
)
"""The app's modules that safe mode does without (it keeps mqtt and wifi; diagnostics is loaded again for its
one `info`). One string: a tuple of ten would be ten objects on the heap of every boot."""


def load(name: str = STATE):
    """The update's state (a dict), or None when there is none (or it cannot be read: then there is none)."""
    try:
        with open(name) as f:
            st = json.load(f)
        return st if type(st) is dict else None
    except (OSError, ValueError):
        return None


def save(st) -> None:
    """Write the state whole: a temporary file, then a rename over the old one."""
    with open("ota.jtmp", "w") as f:
        json.dump(st, f)
    os.rename("ota.jtmp", STATE)


def remove(name: str) -> None:
    try:
        os.remove(name)
    except OSError:
        pass


def exists(name: str) -> bool:
    try:
        os.stat(name)
        return True
    except OSError:
        return False


def clear(st, suffix: str, state: str = STATE) -> None:
    """Remove `<name><suffix>` of each of the update's files, then the state: the update is over."""
    for name in st.get("files", ()):
        remove(name + suffix)
    remove(state)


def rollback(st) -> None:
    """Put each `.bak` back (a file that had none was new with the update and stays, unused); idempotent, so
    a power cut during it is finished at the next boot. A configuration's: "config.rolled" tells the next boot
    (the app's first `info`), and a reset, as main.py parsed the new config.json."""
    print("ota: rollback")
    files = st.get("files", ())
    for name in files:
        if exists(name + ".bak"):
            remove(name)
            os.rename(name + ".bak", name)
    clear(st, ".tmp")
    if "config.json" in files:
        with open("config.rolled", "w") as f:
            f.write("1")
        import machine

        machine.reset()


def swap(st, feed=None) -> None:
    """Each `<name>.tmp` in, its old file kept as `<name>.bak`; safe to run again from any point. `feed`: the
    watchdog's, once a file (two renames on the flash)."""
    for name in st["files"]:
        if feed is not None:
            feed()
        tmp = name + ".tmp"
        if exists(tmp):
            if exists(name):
                if exists(name + ".bak"):
                    os.remove(name)
                else:
                    os.rename(name, name + ".bak")
            os.rename(tmp, name)
    st["stage"] = "trial"
    st["boots"] = 0
    save(st)
    print("ota: swapped", st.get("version"))


def boot(cfg) -> None:
    """Called by main.py with the parsed config before `import app`: the backups of a confirmed update go (the
    app confirmed it by renaming the state `ota.ok`: health.apply); then count this boot in a pending update's
    state; in `fetch` or `swap` run the updater (which resets the board: never returns); a trial that has used
    its boots is rolled back; past MAX_BOOTS in update mode the update is abandoned."""
    st = load("ota.ok")
    if st is not None:
        clear(st, ".bak", "ota.ok")
        print("ota: backups removed")
    if exists("wifi.fallback"):  # app.py's marker: no known network joined
        __import__("fallback_ap").serve(cfg)  # never returns, but without an update key; 11 characters: no qstr
    if exists("config.rolled"):
        cfg["last_error"] = "config: rolled back"  # app.Node's first
        remove("config.rolled")
    late = exists("ota.offline")
    if late:  # a trial not online in time (health.py): rolled back now
        os.rename("ota.offline", STATE)
    st = load()
    if st is None:
        loops(cfg)
        return
    stage = st.get("stage")
    boots = MAX_BOOTS + 1 if late else st.get("boots", 0) + 1
    st["boots"] = boots
    if boots > MAX_BOOTS:
        if stage == "fetch" or stage == "config":
            print("ota: abandoned")
            clear(st, ".tmp")
        else:
            rollback(st)
        return
    if stage not in ("fetch", "swap", "trial", "config"):
        remove(STATE)
        return
    save(st)
    if stage == "trial":
        cfg["trial"] = 1  # the app says so in `info` until it confirms (health.apply)
    if stage == "swap":  # here, not in the updater: a swap cut short may have moved updater.mpy out
        swap(st)
        import machine

        machine.reset()
    elif stage != "trial":  # fetch, config
        import updater

        updater.update(cfg, st)


def loops(cfg) -> None:
    """Count this boot in LOOPS if a watchdog or an exception reset the board (reset causes 1-3: hardware and
    software watchdog, exception; diagnostics.RESET_NAMES), clear it after a power-on or the reset pin (0, 6);
    at MAX_BOOTS counted, safe mode instead of the app (never returns)."""
    import machine

    cause = machine.reset_cause()
    if cause == 0 or cause == 6:
        remove(LOOPS)
        return
    if not 1 <= cause <= 3:
        return
    try:
        with open(LOOPS) as f:
            n = int(f.read())
    except (OSError, ValueError):
        n = 0
    n += 1
    with open(LOOPS, "w") as f:
        f.write(str(n))
    if n >= MAX_BOOTS:
        import safemode

        safemode.safe(cfg, "safe: %d resets in a row" % n)


def failed(cfg, exc) -> None:
    """`import app` or its setup raised (main.py): roll a trial back and reset; with nothing to roll back to,
    safe mode (safemode.safe: connected, watchdog fed, waiting for an update), never the REPL. Every module the
    app loaded and safe mode does not use (APP_ONLY) is dropped first: safe mode needs the heap."""
    import sys

    print("app failed:", exc)
    for name in APP_ONLY.split():
        sys.modules.pop(name, None)
    import gc

    gc.collect()
    st = load()
    if st is not None and st.get("stage") == "trial":
        rollback(st)
        import machine

        machine.reset()
    import safemode

    safemode.safe(cfg, "safe: " + str(exc))
