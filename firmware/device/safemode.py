"""Safe mode, and the `info` that update and safe modes send (they run without the app's diagnostics loop).

Safe mode (`safe`, otaboot.failed: `import app` or its setup failed and there is nothing to roll back to): join
Wi-Fi and connect as update mode does (updater.Link), say why in `info` (`safe: <error>`), then wait up to SAFE_MS
for a command with the watchdog fed: `update` starts one (the same state command.py writes), `restart` resets; a
reset after SAFE_MS tries the app again. Never the REPL: a bad app can be replaced over the air.
"""

import gc
import json
import time

import machine
import otaboot
import updater

SAFE_MS = 600000


class _Who:
    """What diagnostics.info reads of a NodeLogic, for a node whose app is not loaded."""

    def __init__(self, cfg, base: str) -> None:
        self.node = cfg["node"]
        self.heartbeat_ms = cfg["heartbeat_ms"]
        self.status_topic = base + "status"


def info(link, error: str) -> None:
    """`nodes/<node>/info` saying `error` (schemas.messages.NodeInfo, by diagnostics.info when it loads)."""
    cfg = link.cfg
    up = time.ticks_diff(time.ticks_ms(), link.started) // 1000
    try:
        import diagnostics

        topic, payload, _r, _q = diagnostics.info(
            _Who(cfg, link.base), up, 1, machine.reset_cause(), None, None, error, 0
        )
    except Exception:  # the app's own diagnostics are broken too: the fields every NodeInfo has
        topic = link.base + "info"
        payload = '{"v":1,"node":"%s","fw":"unknown","reset":"unknown","uptime_s":%d,"reconnects":0}' % (
            cfg["node"],
            up,
        )
    try:
        link.client.publish(topic, payload.encode(), True, 1)
    except OSError:
        pass
    print("info:", error)


def safe(cfg, why: str) -> None:
    """Safe mode (otaboot.failed): say `why` in `info`, then wait up to SAFE_MS for a command: `update` starts
    one, `restart` resets. Never returns."""
    if not cfg:  # the app's setup had cleared it
        import nodeconfig

        cfg = nodeconfig.load("config.json")
    gc.collect()
    link = updater.Link(cfg, "command")
    try:
        link.up()
        info(link, why)
        client = link.client
        while time.ticks_diff(time.ticks_ms(), link.started) < SAFE_MS:
            body = client.poll()
            if body is None:
                client.maintain()
                link.sleep(50)
                continue
            try:
                d = json.loads(body)
                cmd = d["command"]
                digest = d.get("manifest")
                if cmd == "update" and type(digest) is str and len(digest) == 64:
                    otaboot.save({"stage": "fetch", "manifest": digest, "boots": 0})
                    break
                if cmd == "restart":
                    break
            except Exception:  # no single message stops safe mode
                print("bad command")
    except Exception as exc:
        print("safe:", exc)
        link.sleep(1000)
    machine.reset()
