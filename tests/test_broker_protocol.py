"""A strict protocol on both brokers, and a protocol fuzz suite (Hypothesis) over raw sockets.

The brokers run as processes (`wsnav broker run`, `mosquitto -c` from the generated config). Every packet is
built by hand, sent over its own TCP connection, and followed by a PINGREQ probe: the broker must answer with
well-formed packets only, then either PINGRESP (it is still serving us) or end the connection, within a few
seconds; a packet MQTT 3.1.1 calls malformed must end the connection; a SUBACK never grants more than asked or
a QoS above 2. After each suite the broker still serves a real login.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.broker_fixtures import Endpoint, client, wait_listening
from tests.conftest import require_tool
from tests.site_fixtures import tiny_site
from wsnav.broker.amqtt.embedded import BrokerProcess
from wsnav.broker.amqtt.packet_gate import BadPacket, check_packet
from wsnav.broker.credentials import write_credentials
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.process import free_port
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

SITE = "tiny"
OWN_TOPIC = topics.zone_state(SITE, "z1", "n1")
ANSWER_S = 3.0
PINGREQ = b"\xc0\x00"
FUZZ = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
    database=None,
)


@pytest.fixture(scope="module", params=["amqtt", "mosquitto"])
def endpoint(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Endpoint]:
    work = tmp_path_factory.mktemp(request.param)
    site = tiny_site(work / "site")
    creds = work / "creds"
    write_credentials(load_site(site).spec, creds)
    if request.param == "amqtt":
        with BrokerProcess(site, creds, data_dir=work / "data") as proc:
            yield Endpoint("amqtt", proc.host, proc.port, creds)
            assert proc.proc is not None and proc.proc.poll() is None, "the broker died"
        return
    mosquitto = require_tool("mosquitto")
    port = free_port()
    root = os.geteuid() == 0
    options = MosquittoOptions(
        bind=("127.0.0.1", port), data_dir=work / "data", user="root" if root else None
    )
    (work / "data").mkdir()
    write_mosquitto_config(load_site(site).spec, creds, work / "conf", options)
    with (work / "mosquitto.log").open("wb") as log:
        proc = subprocess.Popen([mosquitto, "-c", str(work / "conf" / CONF)], stderr=log)
        try:
            wait_listening("127.0.0.1", port, proc)
            yield Endpoint("mosquitto", "127.0.0.1", port, creds)
            assert proc.poll() is None, "mosquitto died"
        finally:
            proc.terminate()
            proc.wait(30)


# --- building packets by hand -------------------------------------------------------------------------------


def remaining_length(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n % 128, n // 128
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


def packet(header: int, body: bytes) -> bytes:
    return bytes([header]) + remaining_length(len(body)) + body


def field(data: bytes) -> bytes:
    return struct.pack("!H", len(data)) + data


@dataclass(frozen=True)
class Connect:
    proto: bytes = b"MQTT"
    level: int = 4
    flags: int = 0x02
    keepalive: int = 30
    client_id: bytes = b"fuzz"
    username: bytes | None = None
    password: bytes | None = None
    will: tuple[bytes, bytes] | None = None

    def body(self) -> bytes:
        out = field(self.proto) + bytes([self.level, self.flags]) + struct.pack("!H", self.keepalive)
        out += field(self.client_id)
        if self.flags & 0x04:
            topic, message = self.will or (b"t", b"m")
            out += field(topic) + field(message)
        if self.flags & 0x80:
            out += field(self.username or b"")
        if self.flags & 0x40:
            out += field(self.password or b"")
        return out

    def bytes(self) -> bytes:
        return packet(0x10, self.body())


def login(ep: Endpoint) -> socket.socket:
    """A raw socket logged in as node n1 (CONNACK 0 read)."""
    sock = socket.create_connection((ep.host, ep.port), timeout=ANSWER_S)
    creds = Connect(flags=0xC2, client_id=b"n1", username=b"n1", password=ep.password("n1").encode())
    sock.sendall(creds.bytes())
    assert read_packets(sock, until=0x20)[0] == (0x20, b"\x00\x00")
    return sock


# --- reading and judging what the broker answers --------------------------------------------------------------

SERVER_TYPES = {0x2, 0x3, 0x4, 0x5, 0x6, 0x7, 0x9, 0xB, 0xD}
"""CONNACK, PUBLISH, PUBACK, PUBREC, PUBREL, PUBCOMP, SUBACK, UNSUBACK, PINGRESP."""


class NoAnswer(AssertionError):
    """Nothing arrived within the wait."""


class Ended(Exception):
    """The broker closed the connection (what it must do to a malformed packet)."""

    def __init__(self, seen: list[tuple[int, bytes]]) -> None:
        super().__init__(f"closed after {seen}")
        self.seen = seen


def _recv_exactly(sock: socket.socket, n: int, seen: list[tuple[int, bytes]]) -> bytes:
    data = b""
    while len(data) < n:
        try:
            chunk = sock.recv(n - len(data))
        except ConnectionResetError:
            chunk = b""
        except TimeoutError:
            raise NoAnswer(f"no answer within {ANSWER_S} s (the broker hangs); got {seen}") from None
        if not chunk:
            raise Ended(seen)
        data += chunk
    return data


def read_packets(sock: socket.socket, until: int) -> list[tuple[int, bytes]]:
    """Server packets up to and including one of type `until` (packet type in the high nibble of the byte);
    raises Ended at end of stream. Anything but a well-formed server packet fails the test."""
    seen: list[tuple[int, bytes]] = []
    while True:
        header = _recv_exactly(sock, 1, seen)[0]
        length, multiplier = 0, 1
        for _ in range(4):
            byte = _recv_exactly(sock, 1, seen)[0]
            length += (byte & 0x7F) * multiplier
            multiplier *= 128
            if not byte & 0x80:
                break
        body = _recv_exactly(sock, length, seen)
        assert header >> 4 in SERVER_TYPES, f"the broker sent packet type {header >> 4}"
        seen.append((header, body))
        if header >> 4 == until >> 4:
            return seen


def answer(sock: socket.socket, data: bytes, until: int = 0xD0) -> list[tuple[int, bytes]] | None:
    """Send `data` (then a PINGREQ when waiting for the PINGRESP); the packets the broker sent up to the one of
    type `until` (excluded when it is the probe's PINGRESP), or None if it closed the connection."""
    try:
        sock.sendall(data + (PINGREQ if until == 0xD0 else b""))
    except OSError:
        return None  # already closed by the broker (e.g. at an oversized header)
    try:
        got = read_packets(sock, until=until)
    except Ended:
        return None
    return got[:-1] if until == 0xD0 else got


def malformed(header: int, body: bytes, first: bool) -> bool:
    try:
        check_packet(header, body, first=first)
    except BadPacket:
        return True
    return False


def assert_still_serving(ep: Endpoint) -> None:
    with client(ep, "n1"):
        pass


# --- the protocol rules the issue listed, on both brokers ------------------------------------------------------


def test_first_packet_that_is_not_connect_is_disconnected(endpoint: Endpoint) -> None:
    with socket.create_connection((endpoint.host, endpoint.port), timeout=ANSWER_S) as sock:
        assert answer(sock, packet(0x30, field(OWN_TOPIC.encode()) + b"x")) is None


@pytest.mark.parametrize(
    "bad",
    [
        packet(0x30, field(f"wsn/{SITE}/zones/+/state/n1".encode()) + b"x"),  # wildcard topic
        packet(0x30, field(f"wsn/{SITE}/#".encode()) + b"x"),
        packet(0x36, field(OWN_TOPIC.encode()) + b"\x00\x01x"),  # QoS 3
        packet(0x82, b"\x00\x01" + field(OWN_TOPIC.encode()) + b"\x03"),  # SUBSCRIBE asking QoS 3
        packet(0x80, b"\x00\x01" + field(OWN_TOPIC.encode()) + b"\x01"),  # SUBSCRIBE reserved flags
        packet(0x30, field(b"wsn/\xff\xfe") + b"x"),  # topic not UTF-8
        packet(0x32, field(OWN_TOPIC.encode()) + b"\x00\x00x"),  # QoS 1 with packet id 0
        packet(0x10, Connect().body()),  # a second CONNECT
    ],
    ids=["plus", "hash", "qos3", "sub-qos3", "sub-flags", "utf8", "pid0", "connect-twice"],
)
def test_malformed_packet_after_login_is_disconnected(endpoint: Endpoint, bad: bytes) -> None:
    with login(endpoint) as sock:
        assert answer(sock, bad) is None


def test_client_id_that_is_not_utf8_is_refused(endpoint: Endpoint) -> None:
    bad = Connect(flags=0xC2, client_id=b"n1\xff", username=b"n1", password=endpoint.password("n1").encode())
    with socket.create_connection((endpoint.host, endpoint.port), timeout=ANSWER_S) as sock:
        got = answer(sock, bad.bytes())
        assert got is None


# --- the fuzz suite ---------------------------------------------------------------------------------------------

TEXTS = st.one_of(
    st.sampled_from([OWN_TOPIC, f"wsn/{SITE}/#", f"wsn/{SITE}/+/x", "a/b#", "+", "#", "", "a\x00b", "wsn/é"]),
    st.text(max_size=20),
).map(lambda s: s.encode("utf-8", "surrogatepass"))
RAW = st.one_of(TEXTS, st.binary(max_size=24))
VALID_FILTERS = st.sampled_from([OWN_TOPIC, f"wsn/{SITE}/#", f"wsn/{SITE}/zones/+/state/n1", "a/b"]).map(
    str.encode
)
FILTERS = st.one_of(VALID_FILTERS, VALID_FILTERS, TEXTS)
"""Mostly well-formed filters, so the fuzz reaches the broker's SUBACK logic and not only its parser."""


@st.composite
def connects(draw: st.DrawFn) -> Connect:
    return Connect(
        proto=draw(st.sampled_from([b"MQTT", b"MQIsdp", b"MQT", b""]) | st.binary(max_size=6)),
        level=draw(st.sampled_from([3, 4, 5]) | st.integers(0, 255)),
        flags=draw(st.integers(0, 255)),
        keepalive=draw(st.integers(0, 65535)),
        client_id=draw(st.sampled_from([b"n1", b"robot1", b"operator-zone-sim", b""]) | RAW),
        username=draw(st.sampled_from([b"n1", b"operator", b"nobody"]) | RAW),
        password=draw(st.binary(max_size=40)),
        will=(draw(TEXTS), draw(st.binary(max_size=20))),
    )


@given(connect=connects())
@FUZZ
def test_fuzzed_connect(endpoint: Endpoint, connect: Connect) -> None:
    data = connect.bytes()
    with socket.create_connection((endpoint.host, endpoint.port), timeout=ANSWER_S) as sock:
        got = answer(sock, data)
    bad = malformed(data[0], connect.body(), first=True)
    if got is not None:
        assert got and got[0][0] == 0x20, f"no CONNACK first: {got}"
        assert not (bad and endpoint.kind == "amqtt"), f"amqtt served a malformed CONNECT: {connect}"


@st.composite
def publishes(draw: st.DrawFn) -> tuple[int, bytes]:
    flags = draw(st.integers(0, 15))
    topic = draw(st.one_of(VALID_FILTERS, TEXTS, st.binary(max_size=12)))
    body = field(topic)
    if (flags >> 1) & 3:
        body += struct.pack("!H", draw(st.sampled_from([0, 1, 65535]) | st.integers(0, 65535)))
    return 0x30 | flags, body + draw(st.binary(max_size=64))


@given(pub=publishes())
@FUZZ
def test_fuzzed_publish(endpoint: Endpoint, pub: tuple[int, bytes]) -> None:
    header, body = pub
    if body[2:].startswith(b"$"):
        return  # '$' topics: amqtt closes, Mosquitto drops them quietly (ACL); both are correct
    with login(endpoint) as sock:
        got = answer(sock, packet(header, body))
    if malformed(header, body, first=False):
        assert got is None, f"a malformed PUBLISH was answered with {got}"
    else:
        assert got is None or all(kind >> 4 in (0x4, 0x5) for kind, _ in got), got


@st.composite
def subscribes(draw: st.DrawFn) -> tuple[int, bytes, list[int]]:
    flags = draw(st.sampled_from([2, 2, 2, 2, 2, 0, 3]))
    body = struct.pack("!H", draw(st.sampled_from([1, 7, 7, 0]) | st.integers(0, 65535)))
    requested = []
    for _ in range(draw(st.integers(0, 3))):
        qos = draw(st.sampled_from([0, 1, 2, 3, 0x80]) | st.integers(0, 255))
        requested.append(qos)
        body += field(draw(FILTERS)) + bytes([qos])
    return 0x80 | flags, body, requested


@given(sub=subscribes())
@FUZZ
def test_fuzzed_subscribe(endpoint: Endpoint, sub: tuple[int, bytes, list[int]]) -> None:
    header, body, requested = sub
    with login(endpoint) as sock:
        got = answer(sock, packet(header, body), until=0x90)  # amqtt may answer a PINGREQ before the SUBACK
    if malformed(header, body, first=False):
        assert got is None, f"a malformed SUBSCRIBE was answered with {got}"
        return
    if got is None:
        return
    subacks = [b for kind, b in got if kind >> 4 == 0x9]
    assert len(subacks) == 1, got
    codes = list(subacks[0][2:])
    assert len(codes) == len(requested)
    for code, asked in zip(codes, requested, strict=True):
        assert code == 0x80 or code <= min(asked, 2), (codes, requested)


@given(data=st.binary(min_size=1, max_size=64))
@FUZZ
def test_fuzzed_bytes_after_login(endpoint: Endpoint, data: bytes) -> None:
    """Arbitrary bytes: whatever the broker does, it must not crash, answer garbage (read_packets fails on any
    packet a server may not send), or stop serving others: another client logs in after each example, at once."""
    with login(endpoint) as sock, contextlib.suppress(NoAnswer, OSError):
        sock.settimeout(0.5)
        answer(sock, data)  # an incomplete packet may make the broker wait for more: that is no hang
    started = time.monotonic()
    assert_still_serving(endpoint)
    assert time.monotonic() - started < 5
