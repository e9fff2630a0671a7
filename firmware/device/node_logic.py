"""The zone node's state machine: given sensor readings and the time, what to publish and when. No I/O.

Pure logic shared by the board (`main.py`) and the zone simulator (CPython, up to 1000 nodes in one process), so
the simulator exercises the very decisions the ESP8266 makes. A publication is a tuple
`(topic, payload_bytes, retain, qos)`; the caller sends it with whatever transport it has.

Rules (docs/architecture.md, "The message contract"):
- the zone state is published (retained, QoS 1) on every debounced change and again every heartbeat period,
  so its arrival time tells the robot how fresh it is; it is `clear`, `blocked` or `caution` (a sensor that
  measures distance sees something in the zone that narrows the passage without closing it);
- after every (re)connect: birth `online` (retained) and the current state, whatever happened while offline;
  the heartbeat phase is then shifted by up to half a period, per node (`on_connect`);
- the last will is `offline` (retained);
- `seq` increases with every state publication, from a base the caller picks (random on the board, so a reboot
  does not replay old numbers exactly);
- a PIR fires at random for 30-60 s after power-on: for `warmup_ms` from the first reading or connect (the
  board's boot) its readings are ignored and no state is published (birth only), so after a power cut the zones
  do not all say blocked; the state goes out when the warm-up ends.
"""

from debounce import Debouncer, ticks_add, ticks_diff
from payloads import (
    BLOCKED,
    CAUTION,
    CLEAR,
    OFFLINE,
    ONLINE,
    SEQ_MAX,
    node_status_payload,
    node_status_topic,
    zone_state_payload,
    zone_state_topic,
)

QOS_STATE = 1
QOS_STATUS = 1
WORDS = (CLEAR, BLOCKED, CAUTION)
"""The contract word of each debounce level (debounce.CLEAR, BLOCKED, CAUTION)."""


class NodeLogic:
    """One node: debouncer + heartbeat timer + sequence numbers; knows whether the transport is up."""

    def __init__(
        self,
        site: str,
        zone: str,
        node: str,
        on_delay_ms: int,
        off_delay_ms: int,
        heartbeat_ms: int,
        seq_base: int = 0,
        warmup_ms: int = 0,
    ) -> None:
        self.zone = zone
        self.node = node
        self.heartbeat_ms = heartbeat_ms
        self.state_topic = zone_state_topic(site, zone, node)
        self.status_topic = node_status_topic(site, node)
        self.debouncer = Debouncer(on_delay_ms, off_delay_ms)
        self.seq = seq_base % (SEQ_MAX + 1)
        self.connected = False
        self.last_publish_ms = None  # type: int | None
        self.publications = 0
        self.warmup_ms = warmup_ms  # 0 once the warm-up is over (or there is none)
        self._warm_until = None  # type: int | None

    def _warming(self, now_ms: int) -> bool:
        """True while the sensor warms up: `warmup_ms` from the first call (the node's first reading or connect)."""
        if not self.warmup_ms:
            return False
        until = self._warm_until
        if until is None:
            until = self._warm_until = ticks_add(now_ms, self.warmup_ms)
        if ticks_diff(now_ms, until) < 0:
            return True
        self.warmup_ms = 0
        return False

    @property
    def state(self) -> str:
        """The debounced zone state as a contract word."""
        return WORDS[self.debouncer.state]

    def will(self) -> tuple:
        """(topic, payload, retain, qos) for the CONNECT packet's last will."""
        return (self.status_topic, node_status_payload(self.node, OFFLINE), True, QOS_STATUS)

    def birth(self) -> tuple:
        return (self.status_topic, node_status_payload(self.node, ONLINE), True, QOS_STATUS)

    def state_message(self, now_ms: int) -> tuple:
        """The current state as a fresh publication (next seq); restarts the heartbeat period."""
        self.seq = self.seq + 1 if self.seq < SEQ_MAX else 0
        self.last_publish_ms = now_ms
        self.publications += 1
        return (
            self.state_topic,
            zone_state_payload(self.zone, self.node, self.state, self.seq),
            True,
            QOS_STATE,
        )

    def on_connect(self, now_ms: int) -> list:
        """The transport just connected: birth, then the current state (republished after every reconnect).

        The first heartbeat then comes between half a period and a period later, at an offset drawn from `seq`
        (random per board at boot): boards that reconnect together after a broker restart do not heartbeat in
        step from then on."""
        self.connected = True
        if self._warming(now_ms):
            self.last_publish_ms = None
            return [self.birth()]  # the state follows when the warm-up ends
        msgs = [self.birth(), self.state_message(now_ms)]
        self.last_publish_ms = ticks_add(now_ms, -(self.seq % (self.heartbeat_ms // 2 + 1)))
        return msgs

    def on_disconnect(self) -> None:
        """The transport went down: changes are still tracked and sent by the next `on_connect`."""
        self.connected = False

    def step(self, reading, now_ms: int):
        """Feed one raw sensor reading (a debounce level, or a bool: occupied or not); returns a publication
        (change or heartbeat) or None.

        While disconnected the debouncer keeps running but nothing is returned: the state that counts is the
        one at reconnect time, not a backlog.
        """
        if self._warming(now_ms):
            return None
        before = self.debouncer.state
        after = self.debouncer.update(reading, now_ms)
        if not self.connected:
            return None
        if after != before:
            return self.state_message(now_ms)
        last = self.last_publish_ms
        if last is None or ticks_diff(now_ms, last) >= self.heartbeat_ms:
            return self.state_message(now_ms)
        return None
