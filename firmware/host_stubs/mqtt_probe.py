"""Test driver: exercises mqtt.MQTTClient against a scripted fake broker on 127.0.0.1:PORT.

    micropython -X heapsize=44k -m mqtt_probe PORT CASE

Prints one line per step ("connected", "published", "pings N", "error <msg>") for the test to check.
"""

import sys
import time

from mqtt import MQTTClient

port = int(sys.argv[1])
case = sys.argv[2]
c = MQTTClient("n1", "127.0.0.1", port, "n1", "secret-secret-secret", 2, 800)
try:
    c.connect(("wsn/s/nodes/n1/status", b"offline", True, 1))
    print("connected")
    if case == "publish":
        c.publish("wsn/s/zones/z1/state/n1", b"hello", True, 1)
        print("published")
        c.publish("wsn/s/zones/z1/state/n1", b"qos0", False, 0)
        print("published0")
    elif case == "keepalive":
        start = time.ticks_ms()
        while time.ticks_diff(time.ticks_ms(), start) < 3500:
            c.poll()
            c.maintain()
            time.sleep_ms(20)
        print("pings", c.pings)
    elif case == "silent":
        start = time.ticks_ms()
        while time.ticks_diff(time.ticks_ms(), start) < 6000:
            c.poll()
            c.maintain()
            time.sleep_ms(20)
        print("still up")
    c._send(b"\xe0\x00")  # DISCONNECT (the node itself never sends one)
    c.close()
    print("done")
except OSError as exc:
    print("error", exc)
