"""Checks of the pure logic modules that run unchanged on CPython and MicroPython (same assertions on both):
pytest calls each check_* function under CPython, and runs `micropython -m logic_checks` (38 KiB heap) for the
board's VM. Prints "ok N" after N checks passed."""

from backoff import Backoff
from debounce import BLOCKED, CAUTION, CLEAR, Debouncer, ticks_add, ticks_diff
from diagnostics import FIRMWARE_VERSION, INFO_PERIOD_MS, info
from node_logic import NodeLogic
from nodeconfig import valid_id
from payloads import node_status_payload, zone_state_payload, zone_state_topic
from sensing import digital_occupied, echo_us_to_mm, median, ultrasonic_level


def check_debounce_delays_on_and_off():
    d = Debouncer(500, 2000)
    assert d.update(True, 0) == CLEAR
    assert d.pending_ms(100) == 400
    assert d.update(True, 499) == CLEAR
    assert d.update(True, 500) == BLOCKED
    assert d.update(False, 600) == BLOCKED
    assert d.update(False, 2599) == BLOCKED
    assert d.update(False, 2600) == CLEAR


def check_debounce_glitch_restarts_the_timer():
    d = Debouncer(500, 500)
    d.update(True, 0)
    d.update(False, 300)  # glitch over: the on-timer is forgotten
    assert d.update(True, 400) == CLEAR
    assert d.update(True, 899) == CLEAR
    assert d.update(True, 900) == BLOCKED
    assert d.pending_ms(900) == -1


def check_debounce_zero_delay_follows_input():
    d = Debouncer(0, 0)
    assert d.update(True, 5) == BLOCKED
    assert d.update(False, 5) == CLEAR
    assert d.update(CAUTION, 6) == CAUTION


def check_debounce_caution_uses_on_delay_up_and_off_delay_down():
    d = Debouncer(500, 2000)
    assert d.update(CAUTION, 0) == CLEAR and d.pending_ms(0) == 500
    assert d.update(CAUTION, 500) == CAUTION
    assert d.update(BLOCKED, 600) == CAUTION  # caution -> blocked is more severe: on-delay
    assert d.update(BLOCKED, 1100) == BLOCKED
    assert d.update(CAUTION, 1200) == BLOCKED and d.pending_ms(1200) == 2000  # less severe: off-delay
    assert d.update(CAUTION, 3199) == BLOCKED
    assert d.update(CAUTION, 3200) == CAUTION
    assert d.update(CLEAR, 3300) == CAUTION
    assert d.update(CLEAR, 5300) == CLEAR


def check_debounce_flicker_settles_on_the_level_that_held():
    # An object right at the blocking distance: readings alternate blocked/caution. The zone must not stay
    # clear (both are "something there") and goes to caution, the level that held throughout.
    d = Debouncer(500, 2000)
    for t in range(0, 500, 50):
        assert d.update(BLOCKED if t % 100 else CAUTION, t) == CLEAR
    assert d.update(BLOCKED, 500) == CAUTION
    assert d.pending_ms(500) == 500  # and blocked, still read, must now hold on its own
    # Going down from blocked, readings alternate caution/clear: after the off-delay, caution (the most
    # severe level seen), never clear early.
    d = Debouncer(0, 1000)
    d.update(BLOCKED, 0)
    for t in range(100, 1200, 100):
        d.update(CLEAR if t % 200 else CAUTION, t)
    assert d.state == CAUTION
    # A reading the other way restarts the timer: caution -> blocked pending, then clear.
    d = Debouncer(500, 500, CAUTION)
    d.update(BLOCKED, 0)
    d.update(CLEAR, 400)
    assert d.update(CLEAR, 899) == CAUTION and d.update(CLEAR, 900) == CLEAR


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
    assert (
        zone_state_payload("z1", "n1", "blocked", 3)
        == b'{"v":1,"zone":"z1","node":"n1","state":"blocked","seq":3}'
    )
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
    assert n.step(True, 1099) is None
    beat = n.step(True, 1100)
    assert beat is not None and beat[1] == zone_state_payload("z1", "n1", "blocked", 44)
    n.on_disconnect()
    assert n.step(False, 1200) is None and n.step(False, 1300) is None  # cleared while offline
    again = n.on_connect(5000)
    assert again[1][1] == zone_state_payload("z1", "n1", "clear", 45)


def check_node_logic_publishes_caution():
    n = NodeLogic("s", "z1", "n1", 100, 100, 1000, 0)
    n.on_connect(0)
    assert n.step(CAUTION, 0) is None
    msg = n.step(CAUTION, 100)
    assert msg is not None and msg[1] == zone_state_payload("z1", "n1", "caution", 2) and n.state == "caution"
    assert n.step(BLOCKED, 200) is None
    msg = n.step(BLOCKED, 300)
    assert msg is not None and msg[1] == zone_state_payload("z1", "n1", "blocked", 3)
    beat = n.step(True, 1300)  # a bool is still a level: True is blocked
    assert beat is not None and beat[1] == zone_state_payload("z1", "n1", "blocked", 4)


def check_diagnostics_payload():
    n = NodeLogic("s", "z1", "n1", 100, 100, 1000, 0)
    msg = info(n, 3723, 3, 1, -61, 8000, 'OSError: "x"\\y')
    assert msg[0] == "wsn/s/nodes/n1/info" and msg[2:] == (True, 0) and INFO_PERIOD_MS == 300000
    assert msg[1].encode() == (
        b'{"v":1,"node":"n1","fw":"' + FIRMWARE_VERSION.encode() + b'","reset":"watchdog","uptime_s":3723,'
        b'"rssi":-61,"heap_free":8000,"reconnects":2,"error":"OSError: \'x\'/y","heartbeat_ms":1000,'
        b'"bad_commands":0}'
    )
    plain = info(n, 0, 0, 42, 31)[1].encode()  # no link RSSI (the SDK's 31), nothing measured, unknown cause
    assert (
        plain
        == b'{"v":1,"node":"n1","fw":"'
        + FIRMWARE_VERSION.encode()
        + b'","reset":"unknown","uptime_s":0,"reconnects":0,"heartbeat_ms":1000,"bad_commands":0}'
    )
    n.heartbeat_ms = 2000  # a set_heartbeat command
    assert info(n, 0, 1, 0, None, None, None, 3)[1].endswith(',"heartbeat_ms":2000,"bad_commands":3}')


def check_heartbeat_and_debounce_across_the_clock_wrap():
    """Times are ticks (each VM's wrapping clock; 2**30 on the board): a heartbeat, a held-back glitch and the
    delays come out the same when the clock wraps in the middle of them."""
    for t0 in (0, ticks_add(0, -1500), ticks_add(0, -100), ticks_add(0, -30)):
        n = NodeLogic("s", "z1", "n1", 500, 1000, 2000, 0)

        def at(ms):
            return ticks_add(t0, ms)

        n.on_connect(at(0))
        n.last_publish_ms = at(0)  # the heartbeat phase aside
        assert n.step(True, at(100)) is None and n.step(False, at(400)) is None  # a glitch
        assert n.step(False, at(1999)) is None
        beat = n.step(False, at(2000))
        assert beat is not None and n.state == "clear", t0
        assert n.step(True, at(2100)) is None and n.step(True, at(2599)) is None
        assert n.step(True, at(2600)) is not None and n.state == "blocked"
        assert n.debouncer.pending_ms(at(2600)) == -1 and ticks_diff(at(2600), t0) == 2600
        assert n.step(False, at(2700)) is None and n.debouncer.pending_ms(at(3200)) == 500
        assert n.step(False, at(3700)) is not None and n.state == "clear"


def check_pir_warm_up_holds_the_state_back():
    """An HC-SR501 fires at random for up to a minute after power-on: during the warm-up a connect sends the birth
    alone, readings are ignored (no blocked), and the state goes out when it ends, debounced from then on."""
    n = NodeLogic("s", "z1", "n1", 500, 1000, 10000, 0, 60000)
    assert n.step(True, 0) is None  # the first reading starts the warm-up
    msgs = n.on_connect(1000)
    assert [m[0] for m in msgs] == ["wsn/s/nodes/n1/status"]
    for t in range(1000, 60000, 50):  # the pin fires throughout: nothing is published
        assert n.step(True, t) is None, t
    first = n.step(False, 60000)
    assert first is not None and first[1] == zone_state_payload("z1", "n1", "clear", 1)
    assert n.step(True, 60100) is None and n.step(True, 60599) is None
    msg = n.step(True, 60600)
    assert msg is not None and n.state == "blocked"
    again = n.on_connect(61000)  # after the warm-up a reconnect sends the state as usual
    assert len(again) == 2 and again[1][1] == zone_state_payload("z1", "n1", "blocked", 3)


def check_seq_wraps_below_2_to_30():
    n = NodeLogic("s", "z", "n", 0, 0, 1000, 2**30 - 1)
    n.on_connect(0)
    assert n.seq == 0


def check_sensing():
    assert echo_us_to_mm(5831) == 1000  # 5831 us round trip at 343 m/s
    assert echo_us_to_mm(-1) > 4000 and echo_us_to_mm(0) > 4000
    assert median([5, 1, 9]) == 5
    # one wild echo does not decide: median of five
    assert ultrasonic_level([2000, 2100, -1, 1900, 60000], 1000, 0) == BLOCKED
    assert ultrasonic_level([-1, -1, 2000, -2, 30000], 1000, 0) == CLEAR
    # 1000 mm blocks, 2000 mm is the caution band's edge; 8746 us is 1500 mm
    assert ultrasonic_level([8746, 8746, 5000, 60000, -1], 1000, 2000) == CAUTION
    assert ultrasonic_level([8746, 5000, 5000, -1, 1], 1000, 2000) == BLOCKED
    assert ultrasonic_level([8746, -1, -1, -1, 1], 1000, 2000) == CLEAR
    assert ultrasonic_level([8746], 1000, 0) == CLEAR  # no caution band configured
    assert digital_occupied(1, False) and not digital_occupied(1, True) and digital_occupied(0, True)


CHECKS = [v for k, v in sorted(globals().items()) if k.startswith("check_")]


def main():
    for check in CHECKS:
        check()
    print("ok", len(CHECKS))


if __name__ == "__main__":
    main()
