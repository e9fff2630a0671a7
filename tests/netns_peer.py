"""A client run inside a network namespace by tests/test_broker_firewall.py (`ip netns exec NS python -m ...`).

- `flood HOST USER PASS SECONDS`: QoS 0 zone states of node USER as fast as paho takes them;
- `probe HOST USER PASS COUNT BIND`: COUNT QoS 1 zone states of node USER, one every 0.1 s, from address BIND;
- `watch HOST USER PASS SECONDS`: subscribe to every zone state, say `subscribed` once subscribed, then count
  for SECONDS.
Each prints one JSON line: what it sent (the flood also when it stopped), or how many messages it received per
topic and when the last one of each arrived (`last`; time.monotonic(), one clock for every namespace).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections import Counter

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

SITE = "tiny"


def _client(host: str, user: str, password: str, bind: str = "") -> mqtt.Client:
    client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=user)
    client.username_pw_set(user, password)
    client.max_queued_messages_set(0)
    client.connect(host, 1883, bind_address=bind)
    client.loop_start()
    return client


def main() -> None:
    mode, host, user, password, amount = sys.argv[1:6]
    topic = f"wsn/{SITE}/zones/z1/state/{user}" if user == "n1" else f"wsn/{SITE}/zones/z2/state/{user}"
    if mode == "flood":
        client, sent, end = _client(host, user, password), 0, time.monotonic() + float(amount)
        while time.monotonic() < end:
            client.publish(topic, b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":%d}' % sent, qos=0)
            sent += 1
        print(json.dumps({"sent": sent, "ended": time.monotonic()}), flush=True)
        os._exit(0)  # as a flooder that is killed: paho would first send all it queued, at the capped rate
    elif mode == "probe":
        client = _client(host, user, password, bind=sys.argv[6])
        infos = []
        for i in range(int(amount)):
            payload = b'{"v":1,"zone":"z2","node":"%s","state":"clear","seq":%d}' % (user.encode(), i)
            infos.append(client.publish(topic, payload, qos=1))
            time.sleep(0.1)
        for info in infos:
            info.wait_for_publish(30)
        print(
            json.dumps({"sent": len(infos), "acknowledged": sum(i.is_published() for i in infos)}), flush=True
        )
    else:
        got: Counter[str] = Counter()
        last: dict[str, float] = {}

        def on_message(_c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
            got.update([msg.topic])
            last[msg.topic] = time.monotonic()

        client = _client(host, user, password)
        client.on_message = on_message
        subscribed = threading.Event()
        client.on_subscribe = lambda *_a: subscribed.set()
        client.subscribe(f"wsn/{SITE}/zones/#", 1)
        if not subscribed.wait(60):
            sys.exit("watch: no SUBACK within 60 s")
        print("subscribed", flush=True)  # the test starts the senders only now: nothing is sent unwatched
        time.sleep(float(amount))
        print(json.dumps({"got": dict(got), "last": last}), flush=True)
    client.disconnect()
    client.loop_stop()


if __name__ == "__main__":
    main()
