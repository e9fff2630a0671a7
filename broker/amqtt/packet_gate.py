"""A strict MQTT 3.1.1 framing check in front of amqtt: whole packets only, size-capped, well formed.

amqtt 0.12.1 parses whatever arrives and lets many malformed packets through (QoS 3, wildcard PUBLISH topics,
invalid UTF-8 client ids, a first packet that is not CONNECT) and reads any length a client announces. The gate
reads one complete packet at a time from the socket, checks it against the spec and its size cap, and only then
hands its bytes to amqtt; anything else ends the connection, as Mosquitto does. `check_packet` is pure (no I/O)
so it can be tested on its own, and `GateReader` is the `ReaderAdapter` the broker gives amqtt.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable

from amqtt.adapters import ReaderAdapter

from wsnav.broker.identity_limits import MAX_PACKET_BYTES

MAX_BACKLOG_BYTES = 64 * 1024
"""Unread input (in the kernel's socket buffer) a client held to its rate may leave behind before it is
disconnected and the input discarded: about 1,000 zone states, far above any node's burst. A flood left
megabytes there, which kept its messages coming for minutes after the flooder had gone (the peer's FIN waits
behind them)."""

CONNECT, PUBLISH, PUBACK, PUBREC, PUBREL, PUBCOMP = 1, 3, 4, 5, 6, 7
SUBSCRIBE, UNSUBSCRIBE, PINGREQ, DISCONNECT = 8, 10, 12, 14
_FLAGS_0010 = {PUBREL, SUBSCRIBE, UNSUBSCRIBE}
_EMPTY = {PINGREQ, DISCONNECT}
_ID_ONLY = {PUBACK, PUBREC, PUBREL, PUBCOMP}
_FROM_CLIENTS = {CONNECT, PUBLISH, SUBSCRIBE, UNSUBSCRIBE, PINGREQ, DISCONNECT} | _ID_ONLY


class BadPacket(Exception):
    """A packet the broker must answer by closing the connection; str() says why, in a few words."""


class _Body:
    """A cursor over a packet's bytes after the fixed header; running past the end is a BadPacket."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise BadPacket("field runs past the end of the packet")
        chunk = self.data[self.pos : self.pos + n]
        self.pos += n
        return chunk

    def u8(self) -> int:
        return self.take(1)[0]

    def u16(self) -> int:
        return int(struct.unpack("!H", self.take(2))[0])

    def blob(self) -> bytes:
        return self.take(self.u16())

    def text(self, what: str) -> str:
        raw = self.blob()
        try:
            value = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise BadPacket(f"{what} is not valid UTF-8") from None
        if "\x00" in value:
            raise BadPacket(f"{what} contains U+0000")
        return value

    def left(self) -> int:
        return len(self.data) - self.pos


def check_packet(header: int, body: bytes, *, first: bool) -> int:
    """Raise BadPacket unless `header` + `body` is a packet a client may send now; returns the packet type.

    `first`: the connection's first packet, which must be CONNECT (and CONNECT may come only first).
    """
    kind, flags = header >> 4, header & 0x0F
    if first != (kind == CONNECT):
        raise BadPacket("the first packet must be CONNECT, and only the first")
    if kind not in _FROM_CLIENTS:
        raise BadPacket(f"packet type {kind} is not one a client sends")
    if kind == PUBLISH:
        if (flags >> 1) & 0b11 == 3:
            raise BadPacket("PUBLISH with QoS 3")
    elif flags != (0b0010 if kind in _FLAGS_0010 else 0):
        raise BadPacket(f"reserved flags {flags:#06b} on packet type {kind}")
    cursor = _Body(body)
    if kind == CONNECT:
        _check_connect(cursor)
    elif kind == PUBLISH:
        _check_publish(cursor, qos=(flags >> 1) & 0b11)
    elif kind == SUBSCRIBE:
        _check_subscribe(cursor)
    elif kind == UNSUBSCRIBE:
        _packet_id(cursor)
        if not cursor.left():
            raise BadPacket("UNSUBSCRIBE without a topic filter")
        while cursor.left():
            _check_filter(cursor.text("topic filter"))
    elif kind in _ID_ONLY:
        _packet_id(cursor)
    if kind != PUBLISH and cursor.left():
        raise BadPacket(f"{cursor.left()} stray bytes after packet type {kind}")
    return kind


def _check_connect(cursor: _Body) -> None:
    if cursor.text("protocol name") != "MQTT" or cursor.u8() != 4:
        raise BadPacket("not MQTT 3.1.1 (protocol name MQTT, level 4)")
    flags = cursor.u8()
    will, will_qos, will_retain = flags & 0x04, (flags >> 3) & 0b11, flags & 0x20
    if flags & 0x01:
        raise BadPacket("CONNECT reserved flag set")
    if will_qos == 3 or (not will and (will_qos or will_retain)):
        raise BadPacket("CONNECT will flags are inconsistent")
    if flags & 0x40 and not flags & 0x80:
        raise BadPacket("CONNECT password without username")
    cursor.u16()  # keepalive
    cursor.text("client id")
    if will:
        _check_topic(cursor.text("will topic"))
        cursor.blob()
    if flags & 0x80:
        cursor.text("username")
    if flags & 0x40:
        cursor.blob()


def _check_publish(cursor: _Body, qos: int) -> None:
    _check_topic(cursor.text("topic"))
    if qos:
        _packet_id(cursor)


def _check_subscribe(cursor: _Body) -> None:
    _packet_id(cursor)
    if not cursor.left():
        raise BadPacket("SUBSCRIBE without a topic filter")
    while cursor.left():
        _check_filter(cursor.text("topic filter"))
        if cursor.u8() > 2:
            raise BadPacket("SUBSCRIBE asks for QoS above 2 (or sets reserved bits)")


def _packet_id(cursor: _Body) -> None:
    if cursor.u16() == 0:
        raise BadPacket("packet id 0")


def _check_topic(topic: str) -> None:
    if not topic or "+" in topic or "#" in topic or topic.startswith("$"):
        raise BadPacket("topic name is empty, has a wildcard or starts with $")


def _check_filter(topic_filter: str) -> None:
    levels = topic_filter.split("/")
    for i, level in enumerate(levels):
        if ("+" in level and level != "+") or ("#" in level and (level != "#" or i != len(levels) - 1)):
            raise BadPacket("malformed wildcard in topic filter")
    if not topic_filter:
        raise BadPacket("empty topic filter")


async def _exactly(stream: ReaderAdapter, n: int) -> bytes:
    data = await stream.read(n) if n else b""
    if len(data) < n:
        raise asyncio.IncompleteReadError(data, n)
    return data


async def read_packet(stream: ReaderAdapter, max_bytes: int) -> tuple[int, bytes, bytes]:
    """(first byte, encoded remaining length, body) of the next packet; raises BadPacket when oversized.

    Raises asyncio.IncompleteReadError at end of stream.
    """
    header = (await _exactly(stream, 1))[0]
    length, multiplier, encoded = 0, 1, bytearray()
    while True:
        byte = (await _exactly(stream, 1))[0]
        encoded.append(byte)
        length += (byte & 0x7F) * multiplier
        if not byte & 0x80:
            break
        if len(encoded) == 4:
            raise BadPacket("remaining length longer than 4 bytes")
        multiplier *= 128
    if length > max_bytes:
        raise BadPacket(f"packet of {length} bytes is over the {max_bytes}-byte cap")
    return header, bytes(encoded), await _exactly(stream, length)


def _never() -> bool:
    return False


def _nothing() -> int:
    return 0


class GateReader(ReaderAdapter):
    """What amqtt reads from: the bytes of packets that passed `check_packet`, one whole packet at a time.

    It wraps amqtt's own adapter for the transport (TCP, TLS or WebSocket). The first packet must arrive within `connect_timeout_s`; a bad packet calls `reject(reason)` (which closes
    the connection) and then reads as end of stream, so amqtt ends the session the way it ends a vanished one.
    """

    def __init__(
        self,
        stream: ReaderAdapter,
        reject: Callable[[str], None],
        *,
        max_bytes: int = MAX_PACKET_BYTES,
        connect_timeout_s: float = 5.0,
        max_backlog: int = MAX_BACKLOG_BYTES,
    ) -> None:
        self._stream = stream
        self._reject = reject
        self._max = max_bytes
        self._connect_timeout = connect_timeout_s
        self._buffer = bytearray()
        self._first = True
        self._closed = False
        self.connect_seen = asyncio.Event()
        """Set once a well-formed CONNECT has been read (the connection is no longer an idle socket)."""
        self.packet_delay: Callable[[int], float] | None = None
        """Asked with each packet's type after the CONNECT: seconds to wait before handing it on (its identity's
        rate, wsnav.broker.identity_limits); the wait is backpressure, as the socket is not read meanwhile."""
        self.closed_by_us: Callable[[], bool] = _never
        """True once the broker closed the connection (revoked, rejected): nothing more it sent is handed on."""
        self.peer_left: Callable[[], bool] = _never
        """True once the client has closed its side. Asked only when a packet must wait for its rate: what a
        departed client sent over its rate is discarded, or its backlog would keep its flood going after it left."""
        self.backlog: Callable[[], int] = _nothing
        """Bytes the client sent that wait unread in the socket; asked when a packet must wait for its rate."""
        self.max_backlog = max_backlog

    async def read(self, n: int = -1) -> bytes:
        while not self._closed and (n < 0 or len(self._buffer) < n):
            if not await self._next_packet():
                break
        if n < 0:
            n = len(self._buffer)
        chunk = bytes(self._buffer[:n])
        del self._buffer[:n]
        return chunk

    async def _next_packet(self) -> bool:
        try:
            if self._first:
                header, encoded, body = await asyncio.wait_for(
                    read_packet(self._stream, self._max), self._connect_timeout
                )
            else:
                header, encoded, body = await read_packet(self._stream, self._max)
            check_packet(header, body, first=self._first)
        except TimeoutError:
            return self._stop(f"no CONNECT within {self._connect_timeout:g} s")
        except BadPacket as exc:
            return self._stop(str(exc))
        except (asyncio.IncompleteReadError, ConnectionError):
            return self._stop(None)
        if self._first:
            self._first = False
            self.connect_seen.set()
        elif self.closed_by_us():
            return self._stop(None)
        elif self.packet_delay is not None:
            delay = self.packet_delay(header >> 4)
            if delay > 0.0:
                if self.peer_left():
                    return self._stop("the client left with input over its rate (discarded)")
                if (unread := self.backlog()) > self.max_backlog:
                    return self._stop(f"{unread} bytes of input over its rate (discarded)")
                await asyncio.sleep(delay)
                if self.closed_by_us():
                    return self._stop(None)
        self._buffer += bytes([header]) + encoded + body
        return True

    def _stop(self, reason: str | None) -> bool:
        self._closed = True
        if reason is not None:
            self._reject(reason)
        return False

    def feed_eof(self) -> None:
        self._stream.feed_eof()
