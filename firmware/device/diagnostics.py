"""A node's diagnostics message (`nodes/<node>/info`, schemas.messages.NodeInfo), written from its NodeLogic.

Pure logic (MicroPython and CPython), the one writer of this payload (but for `"trial":true`, NodeInfo's last
field, which app.Node._send_info appends during an update's trial: a parameter here cost the 64-bit port's
heap): the board (app.py) sends it after each
connect and every INFO_PERIOD_MS; the zone simulator's emulated nodes do the same, without what only a board
can measure (RSSI, free heap: left out). Retained, QoS 0: no PUBACK wait on the watchdog's time, and a lost one
is replaced at the next period.

What it costs the board decides its shape. The payload is one `%` format, a str of at most ~160 bytes that the
MQTT client sends as it is (mqtt.MQTTClient.publish writes header, topic and payload one after the other, no
packet copy, no `encode`). Few names and few short literals: on the unix port the firmware's interned strings
sit just under the size at which MicroPython allocates its next, ~3.5 KB qstr pool (300 dynamic qstrs), so
every string of 10 characters or less (interned when the module loads) counts; the reset causes are one string.
"""

INFO_PERIOD_MS = 300000
FIRMWARE_VERSION = "0.6.0"
"""Bump it with every change under firmware/device/: it is how an operator tells which boards are behind."""
RESET_NAMES = "power_on watchdog exception soft_wdt soft_reset deep_sleep reset_pin unknown"
"""`machine.reset_cause()` on the ESP8266 is the SDK's rst_info reason, 0..6 in this order (REASON_DEFAULT_RST,
REASON_WDT_RST, REASON_EXCEPTION_RST, REASON_SOFT_WDT_RST, REASON_SOFT_RESTART, REASON_DEEP_SLEEP_AWAKE,
REASON_EXT_SYS_RST); anything else is `unknown` (schemas.messages.ResetCause)."""


def info(
    logic,
    uptime_s: int,
    connects: int,
    reset_cause: int,
    rssi=None,
    heap_free=None,
    error=None,
    bad_commands=0,
) -> tuple:
    """(topic, payload str, retain, qos) of the diagnostics of `logic` (a NodeLogic: its node id and topics),
    `uptime_s` seconds since boot (seconds, not the board's wrapping ms clock: a small int for 34 years),
    `connects` broker connections since boot, `reset_cause` as `machine.reset_cause()` gives it, `error` why the
    link last went down (an exception or text; None if it never did), `bad_commands` the commands it ignored. The heartbeat period is `logic`'s, which a command may change. The caller sends them after each connect
    and every INFO_PERIOD_MS by its own clock. An RSSI outside -127..0 (the ESP8266 says 31 without a link) is
    left out. The error is cut to 32 characters, its quotes and backslashes made `'` and `/`. The payload's
    UTF-8 bytes are byte for byte what the model serialises (payloads.py says why it is built by hand)."""
    payload = (
        '{"v":1,"node":"%s","fw":"%s","reset":"%s","uptime_s":%d%s%s,"reconnects":%d%s,"heartbeat_ms":%d,"bad_commands":%d}'
        % (
            logic.node,
            FIRMWARE_VERSION,
            RESET_NAMES.split()[reset_cause if 0 <= reset_cause < 7 else 7],
            uptime_s,
            ',"rssi":%d' % rssi if rssi is not None and -127 <= rssi <= 0 else "",
            ',"heap_free":%d' % heap_free if heap_free is not None else "",
            connects - 1 if connects > 0 else 0,
            # \\ -> /, " -> ': by code point, as one-character literals would be interned (see above)
            ',"error":"%s"' % str(error)[:32].replace(chr(92), chr(47)).replace(chr(34), chr(39))
            if error is not None
            else "",
            logic.heartbeat_ms,
            bad_commands,
        )
    )
    topic = logic.status_topic[:-6] + "info"  # nodes/<node>/status -> nodes/<node>/info
    return (topic, payload, True, 0)
