"""Test driver: the watchdog budget. The board's main loop (app.Node, mqtt, ultrasonic) in simulated time, with fakes
only where the board meets the radio and the pins (socket, select, DNS, Wi-Fi, time_pulse_us), and the longest
gap between two watchdog feeds recorded.

    micropython -X heapsize=256k -m budget SCENARIO SIM_SECONDS

At 256 KiB, not the board's 38: the fakes (the broker's records, the radio, the DNS) are Python on the same
heap and do not fit beside the node at 38 KiB (MemoryError). The node's own heap is measured elsewhere
(tests/test_firmware_node.py, bench.firmware_heap); this driver measures time between feeds.

Time passes only where the board would block: a socket waiting up to its timeout (forever without one), a DNS
lookup, an HC-SR04 ping, a sleep. Soft timers run in those waits, as the ESP8266 runs them (mp_handle_pending
in every wait). The firmware's `time` is fake_time: ticks that wrap at 2**30 ms as the board's do, started 30 s
before a wrap. Scenarios (the HC-SR04 hears no echo at all, 15 samples: its slowest read, in every one):
- `slow_broker`: the broker answers every packet 1.4 s late (over several 0.5 s reads); the node publishes
  every second;
- `loaded_broker`: as slow_broker, 2.5 s late (a loaded Raspberry Pi's 99th percentile): within the 5 s wait;
- `silent_broker`: TCP accepts, nothing ever comes back;
- `eagain_broker`: as slow_broker, but a read that times out says EAGAIN (as a non-blocking lwIP socket does)
  rather than ETIMEDOUT: silence all the same;
- `trickle_broker`: every answer comes a byte every 2 s: a CONNACK takes 6 s, past the 5 s wait (which must end
  at its deadline, not a packet later);
- `wifi_drop`: online, then the access point goes for 20 s, then comes back;
- `ap_outage`: the node's own wifi.Wifi on the fake radio; the access point goes until the node has tried to
  rejoin 100 times, then comes back: flash_writes counts what the SDK wrote (a connect with credentials);
- `dns_slow`: the broker is a name whose lookup takes 7 s and fails (lwIP's own retries), then resolves;
- `dns_hang`: a lookup that never returns (a wedged radio stack): the feeds must stop, so the watchdog resets;
- `month`: 30 days with a PIR (SIM_SECONDS ignored), fast-forward between windows at the board's own pace around
  each of the three wraps of the ticks (and at the end): changes, a glitch and heartbeats judged in each.
Prints "stat KEY VALUE" lines: gap_max_ms (longest gap between feeds), since_last_feed_ms at the end, feeds,
connects, publications, lookup_fed_ms, pm (the Wi-Fi sleep type after start: 0 is modem sleep off), int_max (the
largest int the node kept), uptime_s, and what the broker received (Record).
"""

import sys

import fake_time

sys.modules["time"] = fake_time  # before the firmware loads: its ticks wrap at 2**30 ms, as the board's do
fake_time.start = fake_time.PERIOD - 30000  # every scenario crosses the wrap 30 s in

import random  # noqa: E402

import app  # noqa: E402
import digital_sensor  # noqa: E402
import mqtt  # noqa: E402
import network  # noqa: E402
import soft_timers  # noqa: E402
import ultrasonic  # noqa: E402
import wifi  # noqa: E402

SCENARIO = sys.argv[1]
SIM_MS = int(sys.argv[2]) * 1000
ETIMEDOUT = 110
EAGAIN = 11
FOREVER_MS = 600000
"""What a socket without a timeout waits for a peer that never answers: far past any watchdog."""


class Sim:
    """The simulated clock (fake_time's); advancing it runs the soft timers that fall due. `speed` > 1 makes the
    node's loop pause last that many times longer: a month passes in fewer iterations."""

    def __init__(self) -> None:
        self.speed = 1

    @property
    def t(self) -> int:
        return fake_time.t

    def ticks_ms(self) -> int:
        return fake_time.ticks_ms()

    def advance(self, ms: int) -> None:
        end = fake_time.t + ms
        while fake_time.t < end:
            fake_time.t = min(end, fake_time.t + 10) if soft_timers._timers else end
            soft_timers._run_timers()

    def sleep_ms(self, ms: int) -> None:
        """The node's loop pause (app.Node's clock)."""
        self.advance(ms * self.speed)


sim = Sim()
fake_time.advance = sim.advance  # the firmware's sleeps (the HC-SR04's) run the soft timers too
soft_timers.install()


class Net:
    """The radio and the broker behind it, as the scenario has them at the current time."""

    def __init__(self) -> None:
        self.delay_ms = 5  # how late the broker answers
        self.trickle_ms = 0  # > 0: its answers come a byte at a time, this far apart
        self.silent = False
        self.wifi_up = True
        self.lookup_ms = 0  # how long a DNS lookup takes; FOREVER_MS: never returns
        self.lookup_fails = False
        self.timeout_errno = ETIMEDOUT  # what a read that times out raises

    def reachable(self) -> bool:
        return self.wifi_up and not self.silent


net = Net()


class Record:
    """What the broker received, judged as it comes (a month of it would not fit in the heap): zone state changes
    against the times `expect` announced, heartbeat gaps, and the uptime each diagnostics message states."""

    def __init__(self) -> None:
        self.word = b""
        self.last_t = -1
        self.expected = []  # (simulated time, word) of the changes to come, in order
        self.changes = 0
        self.wrong = 0  # changes nobody expected, or to the wrong word
        self.late_max = -1  # how long after its due time a change was published (ms)
        self.early = 0
        self.beat_min = -1
        self.beat_max = -1
        self.beat_max_dense = -1
        self.beats = 0
        self.infos = 0
        self.uptime_err_max = 0
        self.phased = True

    def expect(self, t: int, word: bytes) -> None:
        self.expected.append((t, word))

    def published(self, topic: bytes, payload: bytes) -> None:
        t = sim.t
        if topic.endswith(b"/info"):
            i = payload.find(b'"uptime_s":') + 11
            err = abs(int(payload[i : payload.find(b",", i)]) - t // 1000)
            self.infos += 1
            self.uptime_err_max = max(self.uptime_err_max, err)
            return
        if b"/zones/" not in topic:
            return
        i = payload.find(b'"state":"') + 9
        word = payload[i : payload.find(b'"', i)]
        if word != self.word:
            self.phased = not self.word
            if self.word:
                self.changes += 1
                if not self.expected or self.expected[0][1] != word:
                    self.wrong += 1
                else:
                    late = t - self.expected.pop(0)[0]
                    self.early += late < 0
                    self.late_max = max(self.late_max, late)
        elif self.phased:
            self.phased = False  # the first heartbeat after the connect comes at the node's own phase
        else:
            gap = t - self.last_t
            self.beats += 1
            self.beat_min = gap if self.beat_min < 0 else min(self.beat_min, gap)
            self.beat_max = max(self.beat_max, gap)
            if sim.speed == 1 and self.dense_since <= self.last_t:
                self.beat_max_dense = max(self.beat_max_dense, gap)
        self.word = word
        self.last_t = t

    dense_since = 0
    """When the loop last came out of fast-forward: a heartbeat gap from then on is a dense one."""


record = Record()


class FakeSocket:
    """A TCP socket to the broker: answers CONNECT, QoS 1 PUBLISH and PINGREQ `net.delay_ms` later, unless the
    broker is silent or the Wi-Fi is down. Blocks as lwIP's socket does: up to its timeout, forever without."""

    def __init__(self) -> None:
        self.timeout_ms = -1
        self.inbox = []  # (ready_at_ms, bytes)
        self.closed = False

    def settimeout(self, t) -> None:
        self.timeout_ms = -1 if t is None else int(t * 1000)

    def _block(self, ready_at: int) -> bool:
        """Wait until `ready_at` if the timeout allows; False (after waiting the timeout) if it does not."""
        limit = FOREVER_MS if self.timeout_ms < 0 else self.timeout_ms
        wait = ready_at - sim.t
        if wait <= limit:
            sim.advance(max(0, wait))
            return True
        sim.advance(limit)
        return False

    def connect(self, addr) -> None:
        if not net.reachable():
            self._block(sim.t + FOREVER_MS)
            raise OSError(ETIMEDOUT)
        sim.advance(5)

    def send(self, data) -> int:
        data = bytes(data)
        if net.reachable():
            kind = data[0] & 0xF0
            answer = None
            if kind == 0x10:
                answer = b"\x20\x02\x00\x00"
            elif kind == 0xC0:
                answer = b"\xd0\x00"
            elif kind == 0x80:  # SUBSCRIBE (the node's commands): SUBACK, its packet id, QoS 1 granted
                answer = b"\x90\x03" + data[2:4] + b"\x01"
            elif kind == 0x30:
                i = 1
                while data[i] & 0x80:
                    i += 1
                tl = (data[i + 1] << 8) | data[i + 2]
                qos = data[0] & 0x06
                record.published(data[i + 3 : i + 3 + tl], data[i + (5 if qos else 3) + tl :])
                if qos:
                    answer = b"\x40\x02" + data[i + 3 + tl : i + 5 + tl]
            if answer is not None:
                at = sim.t + net.delay_ms
                if net.trickle_ms:
                    for i in range(len(answer)):
                        self.inbox.append((at + i * net.trickle_ms, answer[i : i + 1]))
                else:
                    self.inbox.append((at, answer))
        return len(data)

    def recv(self, n: int) -> bytes:
        if not self.inbox or not net.reachable():
            self._block(sim.t + FOREVER_MS)
            raise OSError(net.timeout_errno)
        ready, data = self.inbox[0]
        if not self._block(ready):
            raise OSError(net.timeout_errno)
        if len(data) <= n:
            self.inbox.pop(0)
            return data
        self.inbox[0] = (ready, data[n:])
        return data[:n]

    def ready(self) -> bool:
        return bool(self.inbox) and self.inbox[0][0] <= sim.t and net.reachable()

    def close(self) -> None:
        self.closed = True


class FakeSocketModule:
    def socket(self) -> FakeSocket:
        return FakeSocket()

    def getaddrinfo(self, host, port):
        return [(2, 1, 0, "", (host, port))]


class FakePoller:
    def __init__(self) -> None:
        self.sock = None

    def register(self, sock, mask) -> None:
        self.sock = sock

    def poll(self, timeout):
        sock = self.sock
        return [(sock, FakeSelect.POLLIN)] if sock is not None and sock.ready() else []


class FakeSelect:
    POLLIN = 1
    POLLERR = 8
    POLLHUP = 16

    def poll(self) -> FakePoller:
        return FakePoller()


class Hung(BaseException):
    """Ends a lookup that never returns: by then the watchdog has long reset the board."""


lookup = [0, 0, -1]  # [in a lookup?, when the current one started, the last feed during it (-1: none yet)]


def fake_lookup(host, port):
    lookup[0] = 1
    lookup[1] = sim.t
    try:
        if net.lookup_ms >= FOREVER_MS:
            sim.advance(40000)
            raise Hung()
        sim.advance(net.lookup_ms)
    finally:
        lookup[0] = 0
    if net.lookup_fails:
        raise OSError(-2)
    return [(2, 1, 0, "", ("192.0.2.7", port))]


class FakeWifi:
    def start(self) -> None:
        pass

    def connected(self) -> bool:
        return net.wifi_up

    def rssi(self) -> int:
        return -60


class Watchdog:
    """Records the longest gap between two feeds, in simulated time (not while the loop runs fast-forward)."""

    def __init__(self) -> None:
        self.last = 0
        self.gap_max = 0
        self.feeds = 0

    def feed(self) -> None:
        gap = sim.t - self.last
        if gap > self.gap_max and sim.speed == 1 and self.last >= record.dense_since:
            self.gap_max = gap
        self.last = sim.t
        self.feeds += 1
        if lookup[0]:
            lookup[2] = sim.t - lookup[1]


def pulse_without_echo(pin, level, timeout_us) -> int:
    """No echo: time_pulse_us waits its timeout twice (for the pulse to start, then for it to end; the ESP8266's
    machine_time_pulse_us), then says so."""
    sim.advance(2 * timeout_us // 1000)
    return -2


class FakePin:
    """A PIR's output: high during the driver's `occupied` intervals of simulated time."""

    IN = 0
    PULL_UP = 1
    occupied = []  # (from, to) in simulated ms

    def __init__(self, pin, mode=0, pull=-1) -> None:
        pass

    def value(self) -> int:
        t = sim.t
        for a, b in FakePin.occupied:
            if a <= t < b:
                return 1
        return 0


def small_int_max() -> int:
    """The largest magnitude of any int the node keeps: each must stay a small int on the ESP8266 (below 2**30),
    or every sum with it allocates."""
    worst = 0
    for obj in (node, node.logic, node.logic.debouncer, node.client, node.wifi_backoff, node.broker_backoff):
        for v in obj.__dict__.values():
            if type(v) is int:
                worst = max(worst, v if v >= 0 else -v - 1)
    return worst


mqtt.socket = FakeSocketModule()  # pyright: ignore[reportAttributeAccessIssue]
mqtt.select = FakeSelect()  # pyright: ignore[reportAttributeAccessIssue]
mqtt.lookup = fake_lookup
digital_sensor.Pin = FakePin  # pyright: ignore[reportAttributeAccessIssue]
ultrasonic.time_pulse_us = pulse_without_echo  # pyright: ignore[reportAttributeAccessIssue]
random.seed(19)

radio = wifi.Wifi("site", "secret")
radio.start()
sdk = getattr(network, "sdk")  # the host stub's: [saved SSID, flash writes, joins, access point out, ...]
pm = getattr(network.WLAN, "pm", 2)  # the host stub's record of config(pm=...); the board boots in 2

MONTH = SCENARIO == "month"
cfg = {
    "site": "s",
    "zone": "z1",
    "node": "n1",
    "on_delay_ms": 1000 if MONTH else 100,
    "off_delay_ms": 2000 if MONTH else 100,
    "heartbeat_ms": 60000 if MONTH else 1000,
    "broker_host": "wsnav-pi.lan" if SCENARIO.startswith("dns") else "192.0.2.7",
    "broker_port": 1883,
    "username": "n1",
    "password": "p" * 24,
    "keepalive_s": 30,
    "warmup_ms": 0,
}
wdt = Watchdog()
sensor = digital_sensor.DigitalSensor(5) if MONTH else ultrasonic.Ultrasonic(12, 14, 1000, 15, 0)
node = app.Node(cfg, sensor, radio if SCENARIO == "ap_outage" else FakeWifi(), wdt, sim)
int_max = 0


def at(t_ms: int) -> None:
    """Run the node until simulated time `t_ms`, a minute at a time, checking its ints after each."""
    global int_max
    while sim.t < t_ms:
        node.run(min(60000, t_ms - sim.t))
        int_max = max(int_max, small_int_max())


def month() -> None:
    """30 days: fast-forward (a 10 s loop pause) between dense windows (the board's 50 ms) around each wrap of
    the ticks and at the end. In each window the PIR fires for 400 ms across the instant (held back by the 1 s
    on-delay), then for 20 s (blocked after 1 s, clear 2 s after it ends); heartbeats every minute."""
    t_wrap = fake_time.PERIOD - fake_time.start
    for x in (t_wrap, t_wrap + fake_time.PERIOD, t_wrap + 2 * fake_time.PERIOD, 30 * 86400000 - 180000):
        sim.speed = 200
        at(x - 60000)
        sim.speed = 1
        record.dense_since = sim.t
        FakePin.occupied = [(x - 200, x + 200), (x + 5000, x + 25000)]
        record.expect(x + 6000, b"blocked")
        record.expect(x + 27000, b"clear")
        at(x + 180000)


if SCENARIO == "slow_broker":
    net.delay_ms = 1400
    at(SIM_MS)
elif SCENARIO == "loaded_broker":
    net.delay_ms = 2500
    at(SIM_MS)
elif SCENARIO == "eagain_broker":
    net.delay_ms = 1400
    net.timeout_errno = EAGAIN
    at(SIM_MS)
elif SCENARIO == "trickle_broker":
    net.trickle_ms = 2000
    at(SIM_MS)
elif SCENARIO == "silent_broker":
    net.silent = True
    at(SIM_MS)
elif SCENARIO == "wifi_drop":
    at(SIM_MS // 3)
    net.wifi_up = False
    at(SIM_MS // 3 + 20000)
    net.wifi_up = True
    at(SIM_MS)
elif SCENARIO == "dns_slow":
    net.lookup_ms = 7000
    net.lookup_fails = True
    at(SIM_MS // 2)
    net.lookup_ms = 300
    net.lookup_fails = False
    at(SIM_MS)
elif SCENARIO == "dns_hang":
    at(SIM_MS // 2)  # online through an address from DNS
    net.lookup_ms = FOREVER_MS
    net.silent = True  # the broker goes, the node reconnects and looks the name up again: it never returns
    try:
        at(SIM_MS)
    except Hung:
        pass
elif SCENARIO == "ap_outage":
    writes_at_boot = sdk[1]  # the first start: the fake flash held no SSID yet
    at(10000)
    sdk[3] = True
    joins = sdk[2]
    while sdk[2] < joins + 100:
        at(sim.t + 60000)
    sdk[3] = False
    at(sim.t + 120000)
    print("stat flash_writes", sdk[1] - writes_at_boot, "joins", sdk[2] - joins)
    print("stat boot_writes", writes_at_boot)
elif MONTH:
    month()
else:
    raise SystemExit("unknown scenario " + SCENARIO)

print("stat gap_max_ms", wdt.gap_max, "since_last_feed_ms", sim.t - wdt.last, "feeds", wdt.feeds)
print("stat connects", node.connects, "publications", node.logic.publications, "errors", node.errors)
print("stat lookup_fed_ms", lookup[2], "pm", pm, "sim_ms", sim.t, "int_max", int_max, "uptime_s", node.uptime_s)
r = record
print("stat changes", r.changes, "wrong", r.wrong, "late_max", r.late_max, "early", r.early, "pending", len(r.expected))
print("stat beats", r.beats, "beat_min", r.beat_min, "beat_max", r.beat_max, "beat_max_dense", r.beat_max_dense)
print("stat infos", r.infos, "uptime_err_max", r.uptime_err_max)
