"""The zone node's main loop: wires config, sensor, node logic, Wi-Fi, MQTT and the watchdog together.

One loop, no other waits: every iteration reads the sensor, feeds node_logic, moves the Wi-Fi/broker connection
state machine one step (each step bounded by socket timeouts), sends what node_logic asks for, keeps the MQTT
link alive with its own pings, and feeds the watchdog only if the loop is healthy. "Healthy" means the loop
completes iterations and the node has not been offline longer than MAX_OFFLINE_MS: past that, the watchdog is
left to reset the board, which is the surest cure for a wedged ESP8266 radio stack.
"""

import gc
import random
import time

for name in (
    "machine",
    "network",
    "payloads",
    "debounce",
    "node_logic",
    "backoff",
    "mqtt",
    "sensing",
    "wifi",
    "diagnostics",
):
    # One at a time, a collection after each: a module's loader temporaries are freed before the next one
    # loads, so what stays is packed together. Imported as one batch, the same modules leave the 38 KiB heap
    # cut into holes of a few blocks (bench.firmware_heap_blocks) and the node fails at setup.
    __import__(name)
    gc.collect()
del name

import diagnostics  # noqa: E402
from backoff import Backoff  # noqa: E402
from debounce import ticks_add, ticks_diff  # noqa: E402
from micropython import const  # noqa: E402
from mqtt import MQTTClient  # noqa: E402
from node_logic import NodeLogic  # noqa: E402

# const() with a leading underscore: inlined by the compiler, no heap at run time.
_LOOP_MS = const(50)
_WAIT_MS = const(5000)
"""Per wait for the broker (CONNACK, PUBACK, a packet): a Raspberry Pi broker under load answers in 0.4-2.5 s at
its 99th percentile, and a shorter wait dropped nodes it would have served. The client reads in steps of at most
0.5 s and feeds the watchdog before each, so no gap between feeds exceeds 0.8 s, half the ~1.6 s after which the
ESP8266 SDK's watchdog may reset the board (the budget table in docs/firmware-esp8266.md)."""
_WIFI_JOIN_TIMEOUT_MS = const(20000)
_MAX_OFFLINE_MS = const(600000)
"""Ten minutes without the broker: stop feeding the watchdog and let it reset the board."""
_FALLBACK_AP_MS = const(300000)
"""Offline (no broker) this long, its last Wi-Fi join timed out: the node resets into its fallback access point
(fallback_ap.py; the marker file `wifi.fallback`, which otaboot.boot looks for), before the watchdog's bound
above. A constant, not config.json's: a setting read here would cost the loop's heap (bench.firmware_heap);
config.json's wifi.fallback_ap false keeps the access point closed (fallback_ap.py reads it)."""
_INFO_RETRY_MS = const(60000)
"""When the diagnostics could not be loaded (no heap), try again after this long, not every iteration."""
_MAX_ERRORS = const(20)
"""Consecutive unexpected exceptions in the loop before it stops feeding the watchdog."""
_HEALTHY_S = const(30)
"""How long after boot the node must be running, its last pass without an error (and, for an update on trial,
online with two states or heartbeats sent after the first connect's), before it counts as healthy
(health.apply): an update is confirmed, the boot-loop count cleared. A first connect proves little: a version whose loop fails 8 s later
was once confirmed at it, then boot-looped with its backups gone."""

_LOG_LINES = const(8)
_LOG_CHARS = const(60)
"""The log ring (`Node.log`): its last 8 lines of at most 60 characters (schemas.messages.NodeLog)."""

_OFFLINE = const(0)
_WIFI_JOINING = const(1)
_BROKER_WAIT = const(2)
_ONLINE = const(3)


def _rand16() -> int:
    return random.getrandbits(16)


class Node:
    """A running node. `sensor` has `reading(feed)` (a debounce level or a bool; a slow sensor calls `feed`
    between its steps), `wifi` has `start()`,
    `connected()` and `rssi()` (or is None: wired); `reset_cause` is `machine.reset_cause()` at boot.

    Time is `clock.ticks_ms()` (the `time` module unless a test gives its own): a tick count that wraps at 2**30
    ms on the ESP8266 (12.4 days), only ever compared with `ticks_diff` and moved with `ticks_add` (debounce's:
    one definition for the whole node). A count of milliseconds since boot would outgrow the board's small ints
    (2**30) and put every sum on the heap."""

    def __init__(self, cfg, sensor, wifi=None, wdt=None, clock=None, reset_cause=0) -> None:
        self.sensor = sensor
        self.wifi = wifi
        self.wdt = wdt
        self.clock = clock if clock is not None else time
        self.logic = NodeLogic(
            cfg["site"],
            cfg["zone"],
            cfg["node"],
            cfg["on_delay_ms"],
            cfg["off_delay_ms"],
            cfg["heartbeat_ms"],
            random.getrandbits(20),
            cfg["warmup_ms"],
        )
        self.client = MQTTClient(
            cfg["node"],
            cfg["broker_host"],
            cfg["broker_port"],
            cfg["username"],
            cfg["password"],
            cfg["keepalive_s"],
            _WAIT_MS,
            self.feed,  # before every blocking step, and from a timer during a DNS lookup (no timeout of its own)
        )
        self.wifi_backoff = Backoff(1000, 60000, _rand16)
        self.broker_backoff = Backoff(500, 30000, _rand16)
        self.phase = _OFFLINE
        self.next_attempt_ms = self.ticks()  # at once (a tick, not 0: the clock may be anywhere)
        self.offline_since_ms = 0
        self.errors = 0
        self.connects = 0
        self.reset_cause = reset_cause
        # Why the broker link last went down, for the diagnostics; at first what otaboot says (a configuration
        # rolled back), under a key named as this attribute: a new name would be a new qstr (diagnostics.py).
        self.last_error = cfg.get("last_error")
        self.info_due_ms = 0
        self.command_id = 0  # the last command applied (command.py): QoS 1 may deliver it again
        self.bad_commands = 0
        # Two ints cost less than one tuple or list of both: the instance's dict has 23 slots for 18 to 23
        # attributes (17 would take 17 slots, 96 B less on the unix port), and a tuple constant is heap too.
        self.uptime_s = 0  # whole seconds since boot, counted from the ticks: small int for 34 years
        self._second = self.ticks()  # the tick at which the current uptime second began
        # Not yet known healthy (health.apply): 2 with an update on trial (otaboot.boot said so), 1 without
        # (the boot-loop count to clear), 0 once done. Names the firmware already has: on the 64-bit unix port
        # its interned strings sit at the edge of a qstr pool (diagnostics.py).
        self.trial = 2 if "trial" in cfg else 1
        # The log ring (log, command.py's `log`). Its name, log's, args' and the command's are names MicroPython
        # already has: on the 64-bit unix port the firmware's own names sit just under a qstr pool's end, and one
        # more at run time costs the next pool, ~3.5 KB in one block (diagnostics.py).
        self.buffer = []

    def log(self, *args) -> None:
        """A line of the serial log, also kept in the ring the `log` command sends (command.py): the last
        _LOG_LINES, each its uptime in seconds and the line, cut to _LOG_CHARS characters (sent as JSON strings,
        escaped there). Never raises: with no heap for it the line is only printed."""
        print(*args)
        try:
            ring = self.buffer
            if len(ring) >= _LOG_LINES:
                ring.pop(0)
            ring.append((str(self.uptime_s) + " " + " ".join([str(a) for a in args]))[:_LOG_CHARS])
        except MemoryError:
            pass

    def ticks(self) -> int:
        """The clock's tick count: an int (a small one on the board), whatever type the stubs give it."""
        return self.clock.ticks_ms()  # pyright: ignore[reportReturnType] (micropython-stubs' opaque _TicksMs)

    # -- health and watchdog -----------------------------------------------------------------------------
    def feed(self) -> None:
        """Feed the watchdog if healthy: fewer than _MAX_ERRORS loop errors in a row, and online or offline for
        less than _MAX_OFFLINE_MS. Called before every blocking step (the MQTT client calls it too)."""
        wdt = self.wdt
        if wdt is None or self.errors >= _MAX_ERRORS:
            return
        if self.phase == _ONLINE or ticks_diff(self.ticks(), self.offline_since_ms) < _MAX_OFFLINE_MS:
            wdt.feed()

    # -- connection state machine --------------------------------------------------------------------------
    def _go_offline(self, now_ms: int, why) -> None:
        if self.phase == _ONLINE:
            self.offline_since_ms = now_ms
        self.client.close()
        self.logic.on_disconnect()
        self.last_error = str(why)
        wifi_up = self.wifi is None or self.wifi.connected()
        self.phase = _BROKER_WAIT if wifi_up else _OFFLINE
        self.next_attempt_ms = ticks_add(now_ms, self.broker_backoff.next_delay_ms())
        self.log("mqtt down:", why)

    def _connect_broker(self, now_ms: int) -> None:
        client = self.client
        try:
            client.connect(self.logic.will(), self.logic.status_topic[:-6] + "command")  # its nodes/<node>/command
            self.feed()
            for topic, payload, retain, qos in self.logic.on_connect(now_ms):
                client.publish(topic, payload, retain, qos)
                self.feed()
        except OSError as exc:
            self._go_offline(now_ms, exc)
            return
        self.broker_backoff.reset()
        self.phase = _ONLINE
        self.connects += 1
        self.info_due_ms = now_ms  # diagnostics at once: the next iteration sends them
        self.log("mqtt up", self.connects)

    def _connection_step(self, now_ms: int) -> None:
        wifi = self.wifi
        if self.phase == _ONLINE:
            if wifi is not None and not wifi.connected():
                self._go_offline(now_ms, "wifi lost")
            return
        if self.phase == _OFFLINE:
            if ticks_diff(now_ms, self.next_attempt_ms) >= 0:
                if wifi is not None:
                    wifi.start()
                self.phase = _WIFI_JOINING
                self.next_attempt_ms = ticks_add(now_ms, _WIFI_JOIN_TIMEOUT_MS)  # while joining: when to give up
            return
        if self.phase == _WIFI_JOINING:
            if wifi is None or wifi.connected():
                self.wifi_backoff.reset()
                self.phase = _BROKER_WAIT
                self.next_attempt_ms = now_ms
            elif ticks_diff(now_ms, self.next_attempt_ms) > 0:
                self.phase = _OFFLINE
                self.next_attempt_ms = ticks_add(now_ms, self.wifi_backoff.next_delay_ms())
                self.log("wifi join timed out")
                if ticks_diff(now_ms, self.offline_since_ms) >= _FALLBACK_AP_MS:
                    open("wifi.fallback", "w").close()  # otaboot.boot: fallback_ap.py, not the app
                    __import__("machine").reset()
            return
        # _BROKER_WAIT
        if wifi is not None and not wifi.connected():
            self.phase = _OFFLINE
            self.next_attempt_ms = now_ms
        elif ticks_diff(now_ms, self.next_attempt_ms) >= 0:
            self._connect_broker(now_ms)

    # -- the loop ----------------------------------------------------------------------------------------
    def iteration(self) -> None:
        """One pass: sense, decide, connect/publish, keep alive. Never waits longer than a socket timeout."""
        now = self.ticks()
        elapsed = ticks_diff(now, self._second)
        if elapsed >= 1000:
            self.uptime_s += elapsed // 1000
            self._second = ticks_add(self._second, elapsed - elapsed % 1000)
        reading = self.sensor.reading(self.feed)
        was_online = self.phase == _ONLINE
        self._connection_step(now)
        if self.phase == _ONLINE:
            try:
                if was_online:
                    msg = self.logic.step(reading, now)
                    if msg is not None:
                        self.client.publish(msg[0], msg[1], msg[2], msg[3])
                    elif ticks_diff(now, self.info_due_ms) >= 0:  # not in the same pass as a state: one send per feed
                        self._send_info(now)
                cmd = self.client.poll()
                if cmd is not None:
                    # command.py loaded for this one command and dropped after (as main.py drops the config
                    # parser): its code is heap the loop needs the rest of the time.
                    import command
                    import sys

                    command.apply(self, cmd, now)
                    del sys.modules["command"]
                self.client.maintain()
            except OSError as exc:
                self._go_offline(now, exc)
        else:
            self.logic.step(reading, now)

    def _send_info(self, now_ms: int) -> None:
        """The retained diagnostics (diagnostics.info, kept loaded: ~1.3 KB on the unix port), a str the client
        writes into its packet buffer without an `encode` copy. Free heap is measured after a collection, as the
        model says. Should a MemoryError still come, the next try is a minute later, not every iteration (which
        would count as loop errors and starve the watchdog)."""
        gc.collect()
        wifi = self.wifi
        try:
            topic, payload, retain, qos = diagnostics.info(
                self.logic,
                self.uptime_s,
                self.connects,
                self.reset_cause,
                wifi.rssi() if wifi is not None else None,
                gc.mem_free(),
                self.last_error,
                self.bad_commands,
            )
            if self.trial == 2:  # NodeInfo.trial, its last field: an update not yet confirmed (health.apply)
                payload = payload[:-1] + ',"trial":true}'
        except MemoryError:
            self.info_due_ms = ticks_add(now_ms, _INFO_RETRY_MS)
            self.log("info: no heap")
            return
        self.info_due_ms = ticks_add(now_ms, diagnostics.INFO_PERIOD_MS)
        self.client.publish(topic, payload, retain, qos)

    def run(self, for_ms: int = -1) -> None:
        """Loop forever (or for `for_ms` of the clock's time, for tests); feeds the watchdog when healthy."""
        clock = self.clock
        start = self.offline_since_ms = self.ticks()
        while for_ms < 0 or ticks_diff(self.ticks(), start) < for_ms:
            try:
                self.iteration()
                self.errors = 0
                if self.trial and self.uptime_s >= _HEALTHY_S:
                    __import__("health").apply(self)  # loaded for this, drops itself (no name kept here)
            except MemoryError:
                gc.collect()
                self.errors += 1
                self.log("MemoryError")
            except Exception as exc:  # a bug must not kill the node silently: count it, let the WDT decide
                self.errors += 1
                self.log("loop error:", exc)
            self.feed()
            clock.sleep_ms(_LOOP_MS)


def sensor_from_config(cfg):
    """The sensor described by a parsed config (nodeconfig.parse), with only that sensor's driver loaded."""
    if cfg["sensor_type"] == "hcsr04":
        from ultrasonic import Ultrasonic

        return Ultrasonic(
            cfg["trigger_pin"], cfg["echo_pin"], cfg["threshold_mm"], cfg["samples"], cfg["caution_mm"]
        )
    from digital_sensor import DigitalSensor

    return DigitalSensor(cfg["pin"], cfg["invert"], cfg["sensor_type"] == "ir_beam")


def setup(cfg) -> Node:
    """The board's node from its parsed config (main.py loads it first): the watchdog started, the sensor's
    driver loaded, the config dict emptied (the node keeps what it needs; the dict's table is heap the loop can
    use). The test drivers and the heap benchmark build the node with this too."""
    import machine

    import wifi

    wdt = machine.WDT()
    sensor = sensor_from_config(cfg)  # loads that sensor's driver only
    gc.collect()
    node = Node(
        cfg,
        sensor,
        wifi.Wifi(cfg["wifi_ssid"], cfg["wifi_password"]),
        wdt,
        None,
        machine.reset_cause(),
    )
    cfg.clear()
    gc.collect()
    return node


def main(cfg) -> None:
    """Board entry point: set the node up and loop forever."""
    node = setup(cfg)
    try:
        node.run()
    except KeyboardInterrupt:
        # Ctrl-C from mpremote: one last feed gives the host a whole watchdog period to start maintenance mode
        # (firmware/deploy.py); after that nothing feeds, and a node left at the REPL resets by itself.
        wdt = node.wdt
        if wdt is not None:
            wdt.feed()
        raise
