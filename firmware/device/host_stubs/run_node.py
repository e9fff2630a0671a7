"""Test driver: the node (app.Node, the board's code) in real time on the MicroPython unix port.

    micropython -X heapsize=38k -m run_node CONFIG

Sensor from the fake pin files ($WSNAV_PINS), fake Wi-Fi, real MQTT. Runs until killed. The broker backoff is
capped at 1 s so a restarted broker is found within seconds. DNS is the real getaddrinfo while the file
$WSNAV_PINS/dns says 0 or is missing; 1: every lookup fails ("dns down HOST"); 2: a lookup never returns ("dns
hang HOST"), as lwIP's can (soft timers run meanwhile, as in lwIP's wait on the board). Lines on stdout ("mqtt up N", "mqtt down: ...")
are what the tests wait for.
"""

import gc
import sys
import time

import nodeconfig

CFG = nodeconfig.load(sys.argv[1])  # first, then dropped, as main.py does on the board
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()

import app  # noqa: E402
import machine  # noqa: E402
import mqtt  # noqa: E402
import sensors  # noqa: E402
import wifi  # noqa: E402
from backoff import Backoff  # noqa: E402


def fake_dns(host, port):
    fault = machine._read("dns", 0)  # pyright: ignore[reportAttributeAccessIssue] (the host stub's)
    if fault:
        print("dns", "down" if fault == 1 else "hang", host)
        import soft_timers

        while fault == 2:
            time.sleep_ms(20)
            soft_timers._run_timers()  # lwIP's wait runs the soft timers
        raise OSError("dns down")
    return real_dns(host, port, 2)  # IPv4 only, as lwIP on the ESP8266


real_dns = mqtt.lookup
mqtt.lookup = fake_dns
node = app.Node(CFG, sensors.from_config(CFG), wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"]), machine.WDT())
node.broker_backoff = Backoff(100, 1000, app._rand16)
gc.collect()
print("heap free", gc.mem_free())
if not CFG["broker_host"][-1:].isdigit():  # a name: the client feeds from a machine.Timer while it looks it up
    import soft_timers  # after the heap is measured: the board has machine.Timer in ROM

    soft_timers.install()
node.run()
