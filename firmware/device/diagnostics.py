"""A node's diagnostics message (`nodes/<node>/info`, schemas.messages.NodeInfo), written from its NodeLogic.

Pure logic (MicroPython and CPython). The zone simulator's emulated nodes send it after every connect and every
INFO_PERIOD_MS, without what only a board can measure (RSSI, free heap: left out). Retained, QoS 0: no PUBACK
wait on the watchdog's time, and a lost one is replaced at the next period. The payload is one `%` format of at
most ~160 bytes.

The board does not send it yet: on the 38 KiB heap (unix port) the firmware has no block left for it after a
reconnect (BENCHMARKS.md, "Node firmware: free heap and the diagnostics message"); the call in app.py waits for
the heap to be freed elsewhere.
"""

INFO_PERIOD_MS = 300000
FIRMWARE_VERSION = "0.2.0"
"""Bump it with every change under firmware/device/: it is how an operator tells which boards are behind."""
RESET_NAMES = ("power_on", "watchdog", "exception", "soft_wdt", "soft_reset", "deep_sleep", "reset_pin", "unknown")
"""`machine.reset_cause()` on the ESP8266 is the SDK's rst_info reason, 0..6 in this order (REASON_DEFAULT_RST,
REASON_WDT_RST, REASON_EXCEPTION_RST, REASON_SOFT_WDT_RST, REASON_SOFT_RESTART, REASON_DEEP_SLEEP_AWAKE,
REASON_EXT_SYS_RST); anything else is `unknown` (schemas.messages.ResetCause)."""


def due(due_ms: int, now_ms: int) -> bool:
    """Once the time the last diagnostics set (`info` returns it) is reached; a connect makes them due at once
    (the caller's business: app.py and the simulator know when they connect)."""
    return now_ms >= due_ms


def info(logic, now_ms: int, connects: int, reset_cause: int, rssi=None, heap_free=None, error=None) -> tuple:
    """(topic, payload, retain, qos, next due time) of the diagnostics of `logic` (a NodeLogic: its node id and
    topics), `connects` broker connections since boot, `reset_cause` as `machine.reset_cause()` gives it, `error`
    why the link last went down (an exception or text; None if it never did). An RSSI outside -127..0 (the
    ESP8266 says 31 without a link) is left out. The error is cut to 32 characters, its quotes and backslashes
    made `'` and `/`. Byte for byte what the model serialises (payloads.py says why it is built by hand)."""
    if error is not None:
        error = str(error)[:32].replace("\\", "/").replace('"', "'")
    payload = '{"v":1,"node":"%s","fw":"%s","reset":"%s","uptime_s":%d%s%s,"reconnects":%d%s}' % (
        logic.node,
        FIRMWARE_VERSION,
        RESET_NAMES[reset_cause if 0 <= reset_cause < 7 else 7],
        now_ms // 1000,
        ',"rssi":%d' % rssi if rssi is not None and -127 <= rssi <= 0 else "",
        ',"heap_free":%d' % heap_free if heap_free is not None else "",
        connects - 1 if connects > 0 else 0,
        ',"error":"%s"' % error if error is not None else "",
    )
    topic = logic.status_topic[:-6] + "info"  # nodes/<node>/status -> nodes/<node>/info
    return (topic, payload.encode(), True, 0, now_ms + INFO_PERIOD_MS)

