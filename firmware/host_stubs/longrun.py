"""Test driver: hours of simulated time through the board's main loop, on a 38 KiB heap.

    micropython -X heapsize=44k -m longrun CONFIG SIM_SECONDS

An accelerated clock: each 50 ms loop period advances simulated time without sleeping, so heartbeats, debounce
delays and backoffs follow simulated time; the MQTT link is real (pings follow real time). The sensor follows a
fixed pattern of simulated time. Prints "stat KEY VALUE ..." lines, among them the lowest free heap seen after each simulated minute.
"""

import gc
import sys

import nodeconfig

CFG = nodeconfig.load(sys.argv[1])
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()

import app  # noqa: E402
import machine  # noqa: E402
import wifi  # noqa: E402
from backoff import Backoff  # noqa: E402


class FastClock:
    def __init__(self) -> None:
        self.t = 0

    def ticks_ms(self) -> int:
        return self.t

    def sleep_ms(self, ms: int) -> None:
        self.t += ms


class PatternSensor:
    """Occupied 20 s of every 97 s, plus a 200 ms glitch every 13 s (the debouncer must hold those back)."""

    def __init__(self, clock) -> None:
        self.clock = clock

    def reading(self, feed=None) -> bool:
        t = self.clock.t
        return (t % 97000) < 20000 or (t % 13000) < 200


def main():
    """In a function: its locals are not interned names (the qstr pool, firmware/device/diagnostics.py)."""
    clock = FastClock()
    app.sensor_from_config(CFG)  # its driver module stays loaded, as on the board; the run reads the pattern
    gc.collect()  # as app.setup does between the sensor and the node
    node = app.Node(
        CFG,
        PatternSensor(clock),
        wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"]),
        machine.WDT(),
        clock,
        machine.reset_cause(),
    )
    node.broker_backoff = Backoff(100, 1000, app._rand16)
    sim_ms = int(sys.argv[2]) * 1000
    gc.collect()
    start_free = gc.mem_free()
    lowest = start_free
    while clock.t < sim_ms:
        node.run(60000)
        gc.collect()
        free = gc.mem_free()
        if free < lowest:
            lowest = free
    print("stat heap_start", start_free, "heap_lowest", lowest, "heap_end", gc.mem_free())
    print("stat publications", node.logic.publications, "connects", node.connects, "errors", node.errors)
    print("stat pings", node.client.pings, "feeds", getattr(machine.WDT, "feeds", -1), "sim_s", clock.t // 1000)
    node.client._send(b"\xe0\x00")  # DISCONNECT: a clean end of the run (no will)
    node.client.close()


main()
