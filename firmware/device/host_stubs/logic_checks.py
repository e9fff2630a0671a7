"""Checks of the pure logic modules that run unchanged on CPython and MicroPython (same assertions on both):
pytest calls each check_* function under CPython, and runs `micropython -m logic_checks` (38 KiB heap) for the
board's VM. Prints "ok N" after N checks passed."""

from backoff import Backoff
from debounce import Debouncer
from node_logic import NodeLogic
from payloads import node_status_payload, valid_id, zone_state_payload, zone_state_topic
from sensing import digital_occupied, echo_us_to_mm, median, ultrasonic_occupied


def check_debounce_delays_on_and_off():
    d = Debouncer(500, 2000)
    assert d.update(True, 0) is False
    assert d.pending_ms(100) == 400
    assert d.update(True, 499) is False
    assert d.update(True, 500) is True
    assert d.update(False, 600) is True
    assert d.update(False, 2599) is True
    assert d.update(False, 2600) is False


def check_debounce_glitch_restarts_the_timer():
    d = Debouncer(500, 500)
    d.update(True, 0)
    d.update(False, 300)  # glitch over: the on-timer is forgotten
    assert d.update(True, 400) is False
    assert d.update(True, 899) is False
    assert d.update(True, 900) is True
    assert d.pending_ms(900) == -1


def check_debounce_zero_delay_follows_input():
    d = Debouncer(0, 0)
    assert d.update(True, 5) is True
    assert d.update(False, 5) is False


def check_backoff_grows_caps_and_jitters():
    values = [0, 65535, 32768]
    i = [0]

    def rand16():
        i[0] += 1
        return values[i[0] % 3]

    b = Backoff(100, 1000, rand16)
    delays = [b.next_delay_ms() for _ in range(8)]
    for n, dly in enumerate(delays):
        full = min(1000, 100 * 2**n)
        assert full // 2 <= dly <= full, (n, dly)
    assert max(delays) <= 1000 and delays[-1] >= 500
    b.reset()
    assert b.next_delay_ms() <= 100


def check_payload_bytes():
    assert zone_state_topic("school", "z1", "n1") == "wsn/school/zones/z1/state/n1"
    assert zone_state_payload("z1", "n1", "blocked", 3) == b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":3}'
    assert node_status_payload("n1", "offline") == b'{"v":1,"node":"n1","status":"offline"}'
    assert valid_id("a-B_9") and not valid_id("a/b") and not valid_id("") and not valid_id("x" * 33)
    assert not valid_id("z+") and not valid_id("z#") and not valid_id(3)


def check_node_logic_publishes_changes_heartbeats_and_reconnects():
    n = NodeLogic("s", "z1", "n1", 100, 100, 1000, 41)
    assert n.step(True, 0) is None  # not connected yet: nothing to send
    assert n.will() == ("wsn/s/nodes/n1/status", b'{"v":1,"node":"n1","status":"offline"}', True, 1)
    first = n.on_connect(0)
    assert [m[0] for m in first] == ["wsn/s/nodes/n1/status", "wsn/s/zones/z1/state/n1"]
    assert first[0][1] == b'{"v":1,"node":"n1","status":"online"}'
    assert first[1] == ("wsn/s/zones/z1/state/n1", zone_state_payload("z1", "n1", "clear", 42), True, 1)
    assert n.step(True, 50) is None
    msg = n.step(True, 100)
    assert msg is not None and msg[1] == zone_state_payload("z1", "n1", "blocked", 43)
    assert n.next_due_ms(100) == 1000
    assert n.step(True, 1099) is None
    beat = n.step(True, 1100)
    assert beat is not None and beat[1] == zone_state_payload("z1", "n1", "blocked", 44)
    n.on_disconnect()
    assert n.step(False, 1200) is None and n.step(False, 1300) is None  # cleared while offline
    again = n.on_connect(5000)
    assert again[1][1] == zone_state_payload("z1", "n1", "clear", 45)


def check_seq_wraps_below_2_to_30():
    n = NodeLogic("s", "z", "n", 0, 0, 1000, 2**30 - 1)
    n.on_connect(0)
    assert n.seq == 0


def check_sensing():
    assert echo_us_to_mm(5831) == 1000  # 5831 us round trip at 343 m/s
    assert echo_us_to_mm(-1) > 4000 and echo_us_to_mm(0) > 4000
    assert median([5, 1, 9]) == 5
    # one wild echo does not decide: median of five
    assert ultrasonic_occupied([2000, 2100, -1, 1900, 60000], 1000) is True
    assert ultrasonic_occupied([-1, -1, 2000, -2, 30000], 1000) is False
    assert digital_occupied(1, False) and not digital_occupied(1, True) and digital_occupied(0, True)


CHECKS = [v for k, v in sorted(globals().items()) if k.startswith("check_")]


def main():
    for check in CHECKS:
        check()
    print("ok", len(CHECKS))


if __name__ == "__main__":
    main()
