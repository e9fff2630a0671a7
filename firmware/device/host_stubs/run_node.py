"""Test driver: the node (app.Node, the board's code) in real time on the MicroPython unix port.

    micropython -X heapsize=38k -m run_node CONFIG

Sensor from the fake pin files ($WSNAV_PINS), fake Wi-Fi, real MQTT. Runs until killed. The broker backoff is
capped at 1 s so a restarted broker is found within seconds. Lines on stdout ("mqtt up N", "mqtt down: ...")
are what the tests wait for.
"""

import gc
import sys

import nodeconfig

CFG = nodeconfig.load(sys.argv[1])  # first, then dropped, as main.py does on the board
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()

import app  # noqa: E402
import machine  # noqa: E402
import sensors  # noqa: E402
import wifi  # noqa: E402
from backoff import Backoff  # noqa: E402

node = app.Node(CFG, sensors.from_config(CFG), wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"]), machine.WDT())
node.broker_backoff = Backoff(100, 1000, app._rand16)
gc.collect()
print("heap free", gc.mem_free())
node.run()
