"""Test driver: the watchdog budget. The board's main loop (app.Node, mqtt, ultrasonic) in simulated time, with fakes
only where the board meets the radio and the pins (socket, select, DNS, Wi-Fi, time_pulse_us), and the longest
gap between two watchdog feeds recorded.

    micropython -X heapsize=38k -m budget SCENARIO SIM_SECONDS

Time passes only where the board would block: a socket waiting up to its timeout (forever without one), a DNS
lookup, an HC-SR04 ping, a sleep. Soft timers run in those waits, as the ESP8266 runs them (mp_handle_pending
in every wait). Scenarios (the HC-SR04 hears no echo at all, 15 samples: its slowest read, in every one):
- `slow_broker`: the broker answers every packet 1.4 s late (within the 1.5 s wait, over one 1 s read); the
  node publishes every second;
- `silent_broker`: TCP accepts, nothing ever comes back;
- `eagain_broker`: as slow_broker, but a read that times out says EAGAIN (as a non-blocking lwIP socket does)
  rather than ETIMEDOUT: silence all the same;
- `trickle_broker`: every answer comes a byte every 600 ms: a CONNACK takes 1.8 s, past the 1.5 s wait (which
  must end at its deadline, not a packet later);
- `wifi_drop`: online, then the access point goes for 20 s, then comes back;
- `dns_slow`: the broker is a name whose lookup takes 7 s and fails (lwIP's own retries), then resolves;
- `dns_hang`: a lookup that never returns (a wedged radio stack): the feeds must stop, so the watchdog resets.
Prints "stat KEY VALUE" lines: gap_max_ms (longest gap between feeds), since_last_feed_ms at the end, feeds,
connects, publications, lookup_fed_ms, pm (the Wi-Fi sleep type after start: 0 is modem sleep off).
"""

import random
import sys
import time

import app
import mqtt
import network
import ultrasonic
import soft_timers
import wifi

SCENARIO = sys.argv[1]
SIM_MS = int(sys.argv[2]) * 1000
ETIMEDOUT = 110
EAGAIN = 11
FOREVER_MS = 600000
"""What a socket without a timeout waits for a peer that never answers: far past any watchdog."""


class Sim:
    """The simulated clock; advancing it runs the soft timers that fall due."""

    def __init__(self) -> None:
        self.t = 0

    def ticks_ms(self) -> int:
        return self.t

    def advance(self, ms: int) -> None:
        end = self.t + ms
        while self.t < end:
            self.t = min(end, self.t + 10)
            soft_timers._run_timers()

    # what ultrasonic.py and app.Clock use of `time`
    def now_ms(self) -> int:
        return self.t

    def sleep_ms(self, ms: int) -> None:
        self.advance(ms)

    def sleep_us(self, us: int) -> None:
        self.advance(us // 1000)


sim = Sim()
soft_timers.now = sim.ticks_ms
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
            elif kind == 0x30 and data[0] & 0x06:
                i = 1
                while data[i] & 0x80:
                    i += 1
                tl = (data[i + 1] << 8) | data[i + 2]
                pid = data[i + 3 + tl : i + 5 + tl]
                answer = b"\x40\x02" + pid
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
    """Records the longest gap between two feeds, in simulated time."""

    def __init__(self) -> None:
        self.last = 0
        self.gap_max = 0
        self.feeds = 0

    def feed(self) -> None:
        gap = sim.t - self.last
        if gap > self.gap_max:
            self.gap_max = gap
        self.last = sim.t
        self.feeds += 1
        if lookup[0]:
            lookup[2] = sim.t - lookup[1]


def pulse_without_echo(pin, level, timeout_us) -> int:
    """No echo: time_pulse_us waits its whole timeout, then says so."""
    sim.advance(timeout_us // 1000)
    return -2


mqtt.socket = FakeSocketModule()  # pyright: ignore[reportAttributeAccessIssue]
mqtt.select = FakeSelect()  # pyright: ignore[reportAttributeAccessIssue]
mqtt.ticks_ms = sim.ticks_ms  # pyright: ignore[reportAttributeAccessIssue]
mqtt.lookup = fake_lookup
ultrasonic.time = sim  # pyright: ignore[reportAttributeAccessIssue]
ultrasonic.time_pulse_us = pulse_without_echo  # pyright: ignore[reportAttributeAccessIssue]
random.seed(19)

radio = wifi.Wifi("site", "secret")
radio.start()
pm = getattr(network.WLAN, "pm", 2)  # the host stub's record of config(pm=...); the board boots in 2

cfg = {
    "site": "s",
    "zone": "z1",
    "node": "n1",
    "on_delay_ms": 100,
    "off_delay_ms": 100,
    "heartbeat_ms": 1000,
    "broker_host": "wsnav-pi.lan" if SCENARIO.startswith("dns") else "192.0.2.7",
    "broker_port": 1883,
    "username": "n1",
    "password": "p" * 24,
    "keepalive_s": 30,
}
wdt = Watchdog()
node = app.Node(cfg, ultrasonic.Ultrasonic(12, 14, 1000, 15, 0), FakeWifi(), wdt, sim)


def at(t_ms: int) -> None:
    """Run the node until simulated time `t_ms`."""
    node.run(t_ms)


if SCENARIO == "slow_broker":
    net.delay_ms = 1400
    at(SIM_MS)
elif SCENARIO == "eagain_broker":
    net.delay_ms = 1400
    net.timeout_errno = EAGAIN
    at(SIM_MS)
elif SCENARIO == "trickle_broker":
    net.trickle_ms = 600
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
else:
    raise SystemExit("unknown scenario " + SCENARIO)

print("stat gap_max_ms", wdt.gap_max, "since_last_feed_ms", sim.t - wdt.last, "feeds", wdt.feeds)
print("stat connects", node.connects, "publications", node.logic.publications, "errors", node.errors)
print("stat lookup_fed_ms", lookup[2], "pm", pm, "sim_ms", sim.t)
