"""A small MQTT 3.1.1 client for the zone node: the code that runs on the board is the code that is tested.

Why not umqtt.simple/robust (frozen in the ESP8266 image): they never send PINGREQ by themselves and block
without timeouts, so a half-open TCP connection (broker rebooted, Wi-Fi access point gone) hangs the node until
the watchdog bites. This client:
- bounds every socket operation by 0.5 s (`_STEP_MS`) and every wait (CONNACK, PUBACK, a packet that has begun)
  by `timeout_ms` overall, a deadline checked before each read (within a packet too);
- calls `feed()` before every step that can block (the board's watchdog budget, docs/firmware-esp8266.md), and
  keeps feeding from a timer while a DNS lookup runs (getaddrinfo takes no timeout);
- sends its own keepalive pings (`maintain`) and declares the link dead when a PINGRESP is overdue;
- subscribes to one topic after the CONNACK (`connect`'s `topic`: the node's commands) and hands the caller,
  from `poll`, the payload of each live (not retained) message on it (command.py sends the DISCONNECT before a
  commanded restart: a node never leaves otherwise, and its will must be published when it goes);
- tolerates every other PUBLISH (amqtt 0.12 sends retained messages matching *other* clients' subscriptions):
  read and thrown away in small chunks, never buffered whole; QoS 1 ones are acknowledged so the broker does
  not resend them;
- raises OSError (MQTTError is one) for every failure, so the caller has one thing to catch.
No QoS 2, no callbacks.
"""

import select
import socket

from micropython import const
from time import ticks_add, ticks_diff, ticks_ms

# const() names with a leading underscore are inlined by the compiler and cost no heap at run time.
_CONNECT = const(0x10)
_CONNACK = const(0x20)
_PUBLISH = const(0x30)
_PUBACK = const(0x40)
_SUBSCRIBE = const(0x82)
_SUBACK = const(0x90)
_PINGREQ = const(0xC0)
_PINGRESP = const(0xD0)

_STEP_MS = const(500)
"""The longest any one socket operation blocks (connect, a send, a read): the watchdog is fed between them. The
ESP8266 SDK's watchdog may reset the board 1.6 s after a feed; half of that is the budget for any gap."""
_ETIMEDOUT = const(110)
_EAGAIN = const(11)
"""What a read that found nothing says on a non-blocking socket (lwIP's answer; a soak run on the unix port saw it
once too): silence, like a timeout, not a dead link; the wait's deadline still bounds it."""
_MAX_UNSOLICITED = const(16)
"""Packets handled per `poll` call, so a flood of retained messages cannot starve the main loop."""
_LOOKUP_FEED_MS = const(500)
_LOOKUP_MAX_MS = const(20000)
"""How long a DNS lookup is fed: lwIP gives up by itself after its retries (about 7 s); one that outlives this
is a wedged radio stack, left to the watchdog."""


class MQTTError(OSError):
    """A protocol-level failure (refused CONNACK, missing PUBACK or PINGRESP, closed connection)."""


def _str(s) -> bytes:
    """An MQTT UTF-8 string: 2-byte big-endian length then the bytes."""
    b = s.encode() if isinstance(s, str) else s
    return bytes((len(b) >> 8, len(b) & 0xFF)) + b


def _fixed(first: int, length: int) -> bytes:
    """Fixed header: packet type/flags byte and the variable-length 'remaining length'."""
    out = bytearray((first,))
    while True:
        byte = length & 0x7F
        length >>= 7
        out.append(byte | 0x80 if length else byte)
        if not length:
            return bytes(out)


_PACKET = memoryview(bytearray(256))
"""Where `publish` assembles each packet: the zone state (~110 B with its topic) and the diagnostics (~190 B)
fit. Allocated once, when the module loads into a still unfragmented heap; the board has one client."""

lookup = socket.getaddrinfo
"""A broker name's DNS lookup; test drivers put a fake DNS server here. (Not on the client: an 18th attribute
would grow its dict, a few hundred bytes of the 38 KiB heap.)"""


class MQTTClient:
    """One connection to the broker; create a new one (or call `connect` again) after any OSError."""

    def __init__(
        self,
        client_id: str,
        host: str,
        port: int = 1883,
        user=None,
        password=None,
        keepalive_s: int = 30,
        timeout_ms: int = 2000,
        feed=None,
    ) -> None:
        """`timeout_ms` bounds each wait for the broker; `feed()`, if given, is the board's watchdog feed: called
        before every socket operation (each at most 0.5 s), and every 500 ms by a timer while a DNS lookup runs."""
        self.client_id = client_id
        self.host = host
        self.port = port
        self.user = user
        self.password = password
        self.keepalive_s = keepalive_s
        self.timeout_ms = timeout_ms
        self.sock = None  # type: socket.socket | None
        self._poller = None
        self._pid = 0
        self._last_tx = 0
        self._ping_sent = None  # when the unanswered PINGREQ went out; None: no ping pending
        self.pings = 0
        self.feed = feed
        self.addr = None  # the broker's address: built once for an IPv4 literal, else the last one DNS gave
        self.sub = None  # type: list | None
        """[the subscribed topic's bytes, then the commands a wait read, oldest first]: one attribute, not two
        (the 17th fills the instance's 17-slot dict; an 18th would grow it: heap)."""

    # -- socket helpers: every call is bounded by the socket timeout, every wait by a deadline --------------
    def _fed(self, ms: int):
        """The socket, after feeding the watchdog, its next operation bounded by `ms`: called before each
        operation that can block."""
        feed = self.feed
        if feed is not None:
            feed()
        sock = self.sock
        if sock is None:
            raise MQTTError("not connected")
        sock.settimeout(ms / 1000)
        return sock

    def _send(self, data) -> None:
        """All of `data` (bytes, or a str: MicroPython sends its UTF-8 bytes), each send bounded and fed."""
        sock = self._fed(_STEP_MS)
        mv = memoryview(data)
        sent = 0
        while sent < len(mv):
            n = sock.send(mv[sent:])
            if not n:
                raise MQTTError("send failed")
            sent += n
        self._last_tx = ticks_ms()

    def _recv(self, n: int, deadline) -> bytes:
        """Exactly n bytes by `deadline` (a ticks_ms value), in reads of at most 0.5 s with a feed before each."""
        data = b""
        while len(data) < n:
            left = ticks_diff(deadline, ticks_ms())
            if left <= 0:
                raise MQTTError("timed out waiting for the broker")
            try:
                more = self._fed(left if left < _STEP_MS else _STEP_MS).recv(n - len(data))
            except OSError as exc:
                if exc.errno == _ETIMEDOUT or exc.errno == _EAGAIN:
                    continue  # one step's worth of silence: feed, then wait for what is left
                raise
            if not more:
                raise MQTTError("connection closed by broker")
            data += more
        return data

    def _skip(self, n: int, deadline) -> bytes:
        """Read n bytes in chunks of at most 128 (an unsolicited message must not cost its size in heap); returns
        the last chunk: all of them, for n <= 128."""
        data = b""
        while n > 0:
            data = self._recv(n if n < 128 else 128, deadline)
            n -= len(data)
        return data

    def _read_packet(self, deadline):
        """Read one packet by `deadline`; returns (type, short_body) where short_body is what we need of it (or b'')."""
        first = self._recv(1, deadline)[0]
        length = 0
        shift = 0
        while True:
            b = self._recv(1, deadline)[0]
            length |= (b & 0x7F) << shift
            if not b & 0x80:
                break
            shift += 7
            if shift > 21:
                raise MQTTError("bad remaining length")
        kind = first & 0xF0
        if kind == _PUBLISH:  # (_PUBLISH, payload) for a command, else (0, ...): read in chunks and dropped
            t = self._recv(2, deadline)
            n = (t[0] << 8) | t[1]
            t = self._skip(n, deadline)  # the topic (its whole, at most 128 bytes)
            sub = self.sub
            # A command: a live message (a retained one never is) on the subscribed topic.
            ours = n <= 128 and sub is not None and not first & 1 and t == sub[0]
            pid = self._recv(2, deadline) if first & 6 else b""  # QoS 1 (or 2): a packet id
            length -= 2 + n + len(pid)
            body = self._skip(length, deadline)
            if (first & 6) == 2:
                self._send(bytes((_PUBACK, 2)) + pid)
            # A command is whole up to 128 bytes (NodeCommand's take at most 120; update mode's client reads its
            # chunks whole: updater.py); a longer one is handed over as b"", which the node counts as malformed.
            return (kind if ours else 0), (body if len(body) == length else b"")
        if length <= 4:
            return kind, self._recv(length, deadline) if length else b""
        self._skip(length, deadline)
        return kind, b""

    def _wait_for(self, kind: int, body=None) -> bytes:
        """Read packets until one of `kind` (and `body`, if given) arrives; bounded by timeout_ms overall, the
        deadline checked before every read (a packet that trickles in cannot stretch the wait)."""
        deadline = ticks_add(ticks_ms(), self.timeout_ms)
        while True:
            k, b = self._read_packet(deadline)
            if k == kind and (body is None or b == body):
                return b
            if k == _PINGRESP:
                self._ping_sent = None
            elif k == _PUBLISH:  # a command: handed over by the next `poll`
                self.sub.append(b)  # pyright: ignore[reportOptionalMemberAccess] (subscribed)

    # -- the protocol -----------------------------------------------------------------------------------
    def connect(self, will=None, topic=None) -> None:
        """Open TCP and do CONNECT/CONNACK (a clean session); `will` is (topic, payload, retain, qos) or None.
        `topic`, if given, is then subscribed to at QoS 1 (SUBSCRIBE/SUBACK: a subscription lasts one
        connection), and `poll` hands over its live messages; a refused one (a broker with an older ACL) is
        said, and the client works on without."""
        self.close()
        addr = self._address()
        sock = socket.socket()
        self.sock = sock
        try:
            self._fed(_STEP_MS).connect(addr)
            flags = 0x02
            payload = _str(self.client_id)
            if will is not None:
                flags |= 0x04 | (will[3] << 3) | (0x20 if will[2] else 0)
                payload += _str(will[0]) + _str(will[1])
            if self.user is not None:
                flags |= 0x80
                payload += _str(self.user)
                if self.password is not None:
                    flags |= 0x40
                    payload += _str(self.password)
            ka = self.keepalive_s
            var = b"\x00\x04MQTT\x04" + bytes((flags, ka >> 8, ka & 0xFF))
            self._send(_fixed(_CONNECT, len(var) + len(payload)) + var + payload)
            body = self._wait_for(_CONNACK)
            if len(body) != 2 or body[1] != 0:
                raise MQTTError("connection refused, code " + (str(body[1]) if len(body) == 2 else "?"))
            if topic is not None:  # SUBSCRIBE: packet id 1 (nothing else is in flight yet), QoS 1
                t = _str(topic)
                packet = bytearray((_SUBSCRIBE, len(t) + 3, 0, 1)) + t  # ids make topics far under 128 bytes
                packet.append(1)
                self._send(packet)
                if self.sub is None:  # kept across connects, with any command not handed over yet
                    self.sub = [t[2:]]
                code = self._wait_for(_SUBACK)  # packet id, then the granted QoS or 0x80
                if len(code) != 3 or code[2] & 0x80:
                    print("refused", topic)
        except Exception:
            self.close()
            raise
        poller = select.poll()
        poller.register(sock, select.POLLIN)
        self._poller = poller
        self._ping_sent = None

    def _address(self):
        """The broker's socket address. An IPv4 literal is parsed once (locally: no DNS query, nothing that can
        hang); a name is looked up at every connect, and when the lookup fails the last address it gave is
        reused. With none yet, fail with one clear message: the caller's backoff retries."""
        host = self.host
        addr = self.addr
        if host[host.rfind(".") + 1 :].isdigit():  # no DNS name's last label is all digits (RFC 3696)
            if addr is None:
                addr = self.addr = socket.getaddrinfo(host, self.port)[0][-1]
            return addr
        timer = None
        feed = self.feed
        if feed is not None:
            feed()
            from machine import Timer  # here: a broker given by address never loads it

            start = ticks_ms()
            timer = Timer(-1)
            timer.init(  # its callback runs while getaddrinfo polls lwIP (mp_handle_pending)
                period=_LOOKUP_FEED_MS,
                mode=Timer.PERIODIC,
                callback=lambda _t: ticks_diff(ticks_ms(), start) < _LOOKUP_MAX_MS and feed(),
            )
        try:
            addr = self.addr = lookup(host, self.port)[0][-1]
        except OSError:
            if addr is None:
                raise MQTTError("cannot resolve " + host)
        finally:
            if timer is not None:
                timer.deinit()
        return addr  # connect() feeds before its next step

    def publish(self, topic: str, payload, retain: bool = False, qos: int = 0) -> None:
        """Send a PUBLISH; with qos=1 wait (bounded) for the matching PUBACK. No retry: the caller reconnects.

        `payload` is bytes or a str (sent as its UTF-8 bytes, as diagnostics.info gives it). The packet is
        assembled in the one buffer allocated at import (`_PACKET`), so a publish needs no new heap block on
        the board's fragmented heap, and goes out in one send: separate small sends would each wait for the
        broker's delayed ACK (Nagle), ~40 ms a message here. One that does not fit goes out in two sends."""
        body = memoryview(payload)
        n = len(topic)  # ids are ASCII: characters are bytes
        head = _fixed(_PUBLISH | (qos << 1) | (1 if retain else 0), n + len(body) + (4 if qos else 2))
        buf = _PACKET
        i = len(head)
        buf[:i] = head
        buf[i] = n >> 8
        buf[i + 1] = n & 0xFF
        buf[i + 2 : i + 2 + n] = memoryview(topic)
        i += 2 + n
        if qos:
            self._pid = pid = self._pid + 1 if self._pid < 0xFFFF else 1
            buf[i] = pid >> 8
            buf[i + 1] = pid & 0xFF
            i += 2
        if i + len(body) <= len(buf):
            buf[i : i + len(body)] = body
            self._send(buf[: i + len(body)])
        else:
            self._send(buf[:i])
            self._send(body)
        if qos:
            self._wait_for(_PUBACK, bytes((self._pid >> 8, self._pid & 0xFF)))

    def poll(self):
        """Handle whatever the broker sent, without blocking when nothing is waiting; returns the first command
        (a live message on the subscribed topic) that came, else None; the next call goes on from there."""
        poller = self._poller
        if poller is None:
            raise MQTTError("not connected")
        sub = self.sub
        if sub is not None and len(sub) > 1:  # read during a wait
            return sub.pop(1)
        for _ in range(_MAX_UNSOLICITED):
            events = poller.poll(0)
            if not events:
                return None
            if events[0][1] & (select.POLLHUP | select.POLLERR):
                raise MQTTError("connection lost")
            kind, body = self._read_packet(ticks_add(ticks_ms(), self.timeout_ms))
            if kind == _PINGRESP:
                self._ping_sent = None
            elif kind == _PUBLISH:
                return body
        return None

    def maintain(self) -> None:
        """Keepalive: ping after half the keepalive period without sending; fail if a PINGRESP is overdue."""
        now = ticks_ms()
        half = self.keepalive_s * 500
        sent = self._ping_sent
        if sent is not None:
            if ticks_diff(now, sent) > max(half, self.timeout_ms):
                raise MQTTError("no PINGRESP from broker")
        elif ticks_diff(now, self._last_tx) >= half:
            self._send(bytes((_PINGREQ, 0)))  # its PINGRESP is collected by `poll` or any later wait
            self._ping_sent = ticks_ms()
            self.pings += 1

    def close(self) -> None:
        sock = self.sock
        self.sock = None
        self._poller = None
        if sock is not None:
            try:
                sock.close()
            except Exception:
                pass
