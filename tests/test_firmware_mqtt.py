"""The firmware's own MQTT client (firmware/device/mqtt.py) on the MicroPython unix port, 38 KiB heap, against a
scripted fake broker: the protocol edge cases a real broker will not produce on demand."""

from __future__ import annotations

import json
import socket
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from wsnav.firmware.testing import NodeProcess, build_for_host, micropython_cmd, micropython_env

Script = Callable[[socket.socket], None]


@pytest.fixture(scope="module")
def host_build(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return build_for_host(tmp_path_factory.mktemp("fw"))


def _recv_exact(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        more = conn.recv(n - len(data))
        if not more:
            raise ConnectionError("client closed")
        data += more
    return data


def read_packet(conn: socket.socket) -> tuple[int, bytes]:
    first = _recv_exact(conn, 1)[0]
    length, shift = 0, 0
    while True:
        b = _recv_exact(conn, 1)[0]
        length |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            break
    return first, _recv_exact(conn, length)


def remaining(n: int) -> bytes:
    out = bytearray()
    while True:
        b, n = n & 0x7F, n >> 7
        out.append(b | 0x80 if n else b)
        if not n:
            return bytes(out)


def publish_packet(topic: bytes, payload: bytes, qos: int, pid: int = 0x1234) -> bytes:
    var = len(topic).to_bytes(2, "big") + topic + (pid.to_bytes(2, "big") if qos else b"")
    return bytes([0x30 | (qos << 1)]) + remaining(len(var) + len(payload)) + var + payload


class FakeBroker:
    """Accepts one connection and runs `script` on it in a thread; records what it saw."""

    def __init__(self, script: Script) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(1)
        self.port = self.sock.getsockname()[1]
        self.script = script
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        conn, _ = self.sock.accept()
        conn.settimeout(20)
        try:
            self.script(conn)
        except BaseException as exc:
            self.error = exc
        finally:
            conn.close()
            self.sock.close()


def run_probe(build: tuple[Path, Path], port: int, case: str) -> str:
    device, stubs = build
    env = micropython_env(device, stubs)
    proc = subprocess.run(
        micropython_cmd("mqtt_probe", str(port), case), env=env, capture_output=True, text=True, timeout=60
    )
    return proc.stdout + proc.stderr


def connect_and_ack(conn: socket.socket, code: int = 0) -> bytes:
    kind, body = read_packet(conn)
    assert kind == 0x10
    conn.sendall(bytes([0x20, 2, 0, code]))
    return body


def test_connect_carries_will_credentials_and_keepalive(host_build: tuple[Path, Path]) -> None:
    seen: dict[str, bytes] = {}

    def script(conn: socket.socket) -> None:
        seen["connect"] = connect_and_ack(conn)
        _kind, body = read_packet(conn)  # QoS 1 publish
        conn.sendall(bytes([0x40, 2]) + body[-7:-5])  # pid sits after the topic, before b"hello"
        read_packet(conn)  # QoS 0
        seen["last"] = bytes([read_packet(conn)[0]])

    broker = FakeBroker(script)
    out = run_probe(host_build, broker.port, "publish")
    broker.thread.join(30)
    assert broker.error is None, broker.error
    assert "published0" in out and "done" in out, out
    body = seen["connect"]
    assert body[:7] == b"\x00\x04MQTT\x04"
    # flags: username, password, will retain, will QoS 1, will, clean session
    assert body[7] == 0x80 | 0x40 | 0x20 | 0x08 | 0x04 | 0x02
    assert body[8:10] == (2).to_bytes(2, "big")
    assert b"wsn/s/nodes/n1/status" in body and b"offline" in body and b"secret-secret-secret" in body
    assert seen["last"] == b"\xe0"


def test_unsolicited_publishes_larger_than_the_heap_are_skipped_and_acked(
    host_build: tuple[Path, Path],
) -> None:
    acks: list[bytes] = []

    def script(conn: socket.socket) -> None:
        connect_and_ack(conn)
        # amqtt sends retained messages the node never subscribed to: here 64 KiB of it, more than the heap.
        conn.sendall(publish_packet(b"wsn/s/robots/r1/status", b"x" * 65536, 1, 0x1234))
        kind, body = read_packet(conn)
        while kind & 0xF6 != 0x32:  # our QoS 1 message is acked before or after the client publishes
            acks.append(bytes([kind]) + body)
            kind, body = read_packet(conn)
        conn.sendall(publish_packet(b"wsn/s/operator/blocks/b1", b"y" * 300, 0))
        conn.sendall(bytes([0x40, 2]) + body[-7:-5])
        kind, body = read_packet(conn)
        while kind != 0x30:
            acks.append(bytes([kind]) + body)
            kind, body = read_packet(conn)
        read_packet(conn)

    broker = FakeBroker(script)
    out = run_probe(host_build, broker.port, "publish")
    broker.thread.join(30)
    assert broker.error is None, (broker.error, out)
    assert "published0" in out and "MemoryError" not in out, out
    assert acks == [b"\x40\x12\x34"]


def test_keepalive_pings_are_sent_by_the_node(host_build: tuple[Path, Path]) -> None:
    pings: list[int] = []

    def script(conn: socket.socket) -> None:
        connect_and_ack(conn)
        while True:
            kind, _ = read_packet(conn)
            if kind == 0xC0:
                pings.append(1)
                conn.sendall(bytes([0xD0, 0]))
            elif kind == 0xE0:
                return

    broker = FakeBroker(script)
    out = run_probe(host_build, broker.port, "keepalive")
    broker.thread.join(30)
    assert "done" in out, out
    assert len(pings) >= 2, out  # keepalive 2 s: a ping after each silent second


def test_missing_pingresp_is_detected(host_build: tuple[Path, Path]) -> None:
    def script(conn: socket.socket) -> None:
        connect_and_ack(conn)
        while True:
            read_packet(conn)  # swallow PINGREQs: a half-open link

    broker = FakeBroker(script)
    out = run_probe(host_build, broker.port, "silent")
    assert "error no PINGRESP from broker" in out, out


def test_refused_connack_and_silent_broker_fail_fast(host_build: tuple[Path, Path]) -> None:
    def refuse(conn: socket.socket) -> None:
        connect_and_ack(conn, 5)

    broker = FakeBroker(refuse)
    out = run_probe(host_build, broker.port, "publish")
    assert "error connection refused, code 5" in out, out

    def silent(conn: socket.socket) -> None:
        read_packet(conn)
        threading.Event().wait(10)

    broker = FakeBroker(silent)
    out = run_probe(host_build, broker.port, "publish")
    assert out.startswith("error"), out  # bounded by the socket timeout, not a hang


def test_node_waits_for_a_loaded_broker_that_answers_after_2_5_s(
    host_build: tuple[Path, Path], tmp_path: Path
) -> None:
    """The node itself (run_node: app's wait for the broker) against a broker whose CONNACK and PUBACKs come 2.5 s
    late, a loaded Raspberry Pi's 99th percentile: the node comes online (a 1.5 s wait gave up on it)."""
    late_s = 2.5

    def loaded(conn: socket.socket) -> None:
        kind, _ = read_packet(conn)
        assert kind == 0x10
        threading.Event().wait(late_s)
        conn.sendall(bytes([0x20, 2, 0, 0]))
        while True:
            kind, body = read_packet(conn)
            if kind & 0xF6 == 0x32:  # QoS 1 PUBLISH: its id follows the topic
                tl = int.from_bytes(body[:2], "big")
                threading.Event().wait(late_s)
                conn.sendall(bytes([0x40, 2]) + body[2 + tl : 4 + tl])
            elif kind == 0x82:  # SUBSCRIBE (the node's commands): SUBACK with its packet id, QoS 1 granted
                threading.Event().wait(late_s)
                conn.sendall(bytes([0x90, 3]) + body[:2] + b"\x01")
            elif kind == 0xC0:
                conn.sendall(bytes([0xD0, 0]))

    broker = FakeBroker(loaded)
    config = tmp_path / "config.json"
    config.write_text(
        json.dumps(
            {
                "username": "n1",
                "password": "p" * 24,
                "site": "s",
                "node": "n1",
                "zone": "z1",
                "broker": {"host": "127.0.0.1", "port": broker.port},
                "sensor": {"type": "ir_beam", "pin": 4},
                "heartbeat_s": 60,
                "on_delay_ms": 0,
                "off_delay_ms": 0,
            }
        )
    )
    device, stubs = host_build
    node = NodeProcess(
        micropython_cmd("run_node", str(config)),
        micropython_env(device, stubs, tmp_path / "pins"),
        tmp_path / "node.log",
    )
    try:
        assert node.wait_output("mqtt up 1", 30), node.output()
    finally:
        node.stop()
    assert "mqtt down" not in node.output(), node.output()
