"""Test driver: the node (app.Node, the board's code) in real time on the MicroPython unix port.

    micropython -X heapsize=44k -m run_node CONFIG

Sensor from the fake pin files ($WSNAV_PINS), fake Wi-Fi, real MQTT. Runs until killed. The broker backoff is
capped at 1 s so a restarted broker is found within seconds. DNS is the real getaddrinfo while the file
$WSNAV_PINS/dns says 0 or is missing; 1: every lookup fails ("dns down HOST"); 2: a lookup never returns ("dns
hang HOST"), as lwIP's can (soft timers run meanwhile, as in lwIP's wait on the board). Lines on stdout ("mqtt up N", "mqtt down: ...")
are what the tests wait for. A `restart` command ends the process with status 75 (fake_dns's machine.reset,
as soft_timers.reset does): the test starts it again, as a board reboots.
"""

import gc
import sys

import nodeconfig

CFG = nodeconfig.load(sys.argv[1])  # first, then dropped, as main.py does on the board
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()

import app  # noqa: E402
from backoff import Backoff  # noqa: E402

node = app.setup(CFG)  # as app.main does
node.broker_backoff = Backoff(100, 1000, app._rand16)
gc.collect()
print("heap free", gc.mem_free())
import fake_dns  # noqa: E402  after the heap is measured: the board has no such thing

fake_dns.setup()  # and machine.reset
if not node.client.host[-1:].isdigit():  # a name: the client feeds from a machine.Timer while it looks it up
    import soft_timers  # after the heap is measured: the board has machine.Timer in ROM

    soft_timers.install()
node.run()
