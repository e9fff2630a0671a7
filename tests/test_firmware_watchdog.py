"""The watchdog budget: the board's main loop never goes more than 0.8 s between two watchdog feeds, whatever the
network and the sensor do: half of the ~1.6 s after which the ESP8266 SDK's software watchdog may reset the board
(it checks on a 1.6 s tick: a reset comes 1.6 to 3.2 s after the last feed).

The firmware's own app/mqtt/ultrasonic modules run on the MicroPython unix port in simulated time
(`host_stubs/budget.py`): only the radio and the pins are fakes (socket, select, DNS, Wi-Fi, time_pulse_us), and
time passes only where the board blocks, so the bound is a property of the code, not of this machine's speed.
The HC-SR04 hears no echo in every scenario (15 samples, its slowest read: `time_pulse_us` waits its timeout
twice, ~1.25 s in all, so the driver feeds between pings).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from wsnav.firmware.testing import build_for_host, micropython_env, micropython_exe, parse_stats

BUDGET_MS = 800
SDK_WATCHDOG_MS = 1600
"""The soonest the SDK's watchdog may reset the board after a feed."""
SIM_S = 120


@pytest.fixture(scope="module")
def host_build(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    return build_for_host(tmp_path_factory.mktemp("fw"))


def run_budget(build: tuple[Path, Path], scenario: str, sim_s: int = SIM_S) -> dict[str, int]:
    device, stubs = build
    # The driver's fakes need more than the 38 KiB the node gets (heap is test_firmware_node's concern).
    cmd = [micropython_exe(), "-X", "heapsize=256k", "-m", "budget", scenario, str(sim_s)]
    proc = subprocess.run(
        cmd, env=micropython_env(device, stubs), capture_output=True, text=True, timeout=300
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0 and "Traceback" not in out, out
    print(out)
    return parse_stats(out)


@pytest.mark.parametrize(
    "scenario",
    [
        "slow_broker",
        "loaded_broker",
        "eagain_broker",
        "silent_broker",
        "trickle_broker",
        "wifi_drop",
        "dns_slow",
    ],
)
def test_longest_gap_between_feeds_is_within_the_budget(host_build: tuple[Path, Path], scenario: str) -> None:
    stats = run_budget(host_build, scenario)
    assert stats["gap_max_ms"] <= BUDGET_MS, stats
    assert stats["since_last_feed_ms"] <= BUDGET_MS, stats
    assert stats["errors"] == 0, stats
    assert stats["pm"] == 0, stats  # Wi-Fi modem sleep off (network.WLAN.PM_NONE) once the radio starts
    if scenario in ("slow_broker", "eagain_broker"):  # answers 1.4 s late: the node stays online, publishing
        assert stats["connects"] == 1 and stats["publications"] >= SIM_S // 3, stats
    elif scenario == "loaded_broker":  # 2.5 s late, within the 5 s wait: online once, publishing all along
        assert stats["connects"] == 1 and stats["publications"] >= SIM_S // 6, stats
    elif scenario in ("silent_broker", "trickle_broker"):
        # A CONNACK trickling in a byte every 2 s takes 6 s: past the 5 s wait, checked within the packet.
        assert stats["connects"] == 0, stats
    elif scenario == "wifi_drop":
        assert stats["connects"] == 2, stats
    else:  # dns_slow: fed through each 7 s lookup, online once the name resolves
        assert stats["lookup_fed_ms"] >= 6500 and stats["connects"] == 1, stats


def test_a_lookup_that_never_returns_is_fed_for_a_while_then_left_to_the_watchdog(
    host_build: tuple[Path, Path],
) -> None:
    """getaddrinfo takes no timeout: a timer feeds while lwIP retries, for at most 20 s; a lookup still hanging
    then (a wedged radio stack) goes unfed, so the watchdog resets the board."""
    stats = run_budget(host_build, "dns_hang")
    assert stats["connects"] == 1, stats  # it was online before the broker went and the lookup hung
    assert stats["gap_max_ms"] <= BUDGET_MS, stats
    assert 15000 <= stats["lookup_fed_ms"] <= 20000, stats
    assert stats["since_last_feed_ms"] > SDK_WATCHDOG_MS, stats


def test_a_month_across_the_wraps_of_the_boards_clock(host_build: tuple[Path, Path]) -> None:
    """The ESP8266's ticks_ms wraps at 2**30 ms (12.4 days), and an int from 2**30 on is a heap object there. 30
    simulated days on a clock that wraps as the board's does (three wraps): every time the node keeps stays a
    small int, and heartbeats, debounce and the diagnostics' uptime behave the same around each wrap as anywhere.
    In each window around a wrap the PIR fires for 400 ms across the wrap (held back by the 1 s on-delay), then
    for 20 s (blocked 1 s after it starts, clear 2 s after it ends)."""
    stats = run_budget(host_build, "month", 0)
    assert stats["sim_ms"] >= 30 * 86400 * 1000, stats
    assert stats["int_max"] < 2**30, stats
    assert stats["errors"] == 0 and stats["connects"] == 1, stats
    assert stats["changes"] == 8 and stats["wrong"] == 0 and stats["pending"] == 0, stats  # no glitch got out
    assert stats["early"] == 0 and stats["late_max"] <= 100, stats  # on/off delays kept, to a loop period
    assert stats["beats"] >= 30 * 1440 - 20 and stats["beat_min"] >= 60000, stats
    assert stats["beat_max_dense"] <= 60000 + 100, stats  # in the windows: every minute, to a loop period
    assert stats["infos"] >= 30 * 288 and stats["uptime_err_max"] <= 1, stats
    assert stats["uptime_s"] >= 30 * 86400 - 60, stats
    assert stats["gap_max_ms"] <= BUDGET_MS, stats


def test_rejoining_through_an_access_point_outage_does_not_wear_the_flash(
    host_build: tuple[Path, Path],
) -> None:
    """`WLAN.connect(ssid, password)` makes the ESP8266 SDK write its settings to flash. The node's own wifi.Wifi
    on the fake radio: credentials go in once, at the first start (the radio's flash held another SSID); the
    100 rejoins while the access point is away use the saved settings and write nothing; the node comes back."""
    stats = run_budget(host_build, "ap_outage", 0)
    assert stats["boot_writes"] == 1, stats
    assert stats["joins"] >= 100 and stats["flash_writes"] <= 1, stats
    assert stats["connects"] == 2 and stats["errors"] == 0, stats
    assert stats["gap_max_ms"] <= BUDGET_MS, stats
