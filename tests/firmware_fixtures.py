"""Shared by the firmware's tests: the operator's subscriber that collects what a node on the MicroPython unix port
publishes through the project's broker, and the checks of each payload's exact bytes against the contract."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from tests.conftest import REPO
from wsnav.firmware.testing import SiteBroker
from wsnav.schemas import topics
from wsnav.schemas.credentials import Credentials
from wsnav.schemas.messages import NodeInfo, NodeStatus, ZoneState, parse_payload

SITE_DIR = REPO / "sites" / "school"
SITE = "school"
NODE, ZONE, PIN = "n1", "z1", 5
STATE_TOPIC = topics.zone_state(SITE, ZONE, NODE)
STATUS_TOPIC = topics.node_status(SITE, NODE)
INFO_TOPIC = topics.node_info(SITE, NODE)
WAIT = 60.0


@dataclass
class Msg:
    topic: str
    payload: bytes
    retain: bool


class Subscriber:
    """The operator's paho client over TCP, subscribed to the whole site; collects every message."""

    def __init__(self, broker: SiteBroker, creds: Path) -> None:
        op = Credentials.model_validate_json((creds / "operator.json").read_text())
        self.messages: list[Msg] = []
        self._lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"fwtest-{time.monotonic_ns()}")
        self.client.username_pw_set(op.username, op.password)
        self.client.on_message = self._on_message
        subscribed = threading.Event()
        self.client.on_subscribe = lambda *_a: subscribed.set()
        self.client.connect(broker.host, broker.port)
        self.client.loop_start()
        self.client.subscribe(f"wsn/{SITE}/#", qos=1)
        assert subscribed.wait(WAIT), "subscription not acknowledged"

    def _on_message(self, _c: object, _u: object, msg: mqtt.MQTTMessage) -> None:
        with self._lock:
            self.messages.append(Msg(msg.topic, bytes(msg.payload), bool(msg.retain)))

    def snapshot(self) -> list[Msg]:
        with self._lock:
            return list(self.messages)

    def wait(self, pred: Callable[[Msg], bool], timeout: float = WAIT, after: int = 0) -> Msg:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for m in self.snapshot()[after:]:
                if pred(m):
                    return m
            time.sleep(0.05)
        raise AssertionError(f"no matching message within {timeout} s; got {self.snapshot()[after:]}")

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def state_of(m: Msg) -> ZoneState | None:
    """The validated zone state, checking the exact bytes the firmware sent against the model's own."""
    if m.topic != STATE_TOPIC or not m.payload:
        return None
    zs = parse_payload(ZoneState, m.payload)
    assert zs.to_payload() == m.payload, m.payload
    return zs


def info_of(m: Msg) -> NodeInfo | None:
    """The node's validated diagnostics, its exact bytes checked against the model's own serialisation."""
    if m.topic != INFO_TOPIC or not m.payload:
        return None
    info = parse_payload(NodeInfo, m.payload)
    assert info.to_payload() == m.payload, m.payload
    return info


def is_info(pred: Callable[[NodeInfo], bool] = lambda _i: True) -> Callable[[Msg], bool]:
    return lambda m: (i := info_of(m)) is not None and pred(i)


def is_state(value: str) -> Callable[[Msg], bool]:
    return lambda m: (s := state_of(m)) is not None and s.state == value


def is_status(value: str) -> Callable[[Msg], bool]:
    def pred(m: Msg) -> bool:
        if m.topic != STATUS_TOPIC:
            return False
        st = parse_payload(NodeStatus, m.payload)
        assert st.to_payload() == m.payload, m.payload
        return st.status == value

    return pred
