"""Turning raw sensor signals into "occupied" (or a debounce level): pure arithmetic shared by the board and the zone simulator.

HC-SR04: the echo pulse lasts the sound's round trip, so distance_mm = pulse_us * 343 m/s / 2. A single ping
is noisy (soft clothing, cross-talk), hence the median of N pings; a ping with no echo (timeout, negative from
`machine.time_pulse_us`) means nothing within range and counts as far away.

A distance sensor can say more than occupied or not: something nearer than the blocking threshold closes the
passage (BLOCKED), something between that and the caution threshold narrows it (CAUTION, a high cost for the
robot instead of a wall).
"""

from debounce import BLOCKED, CAUTION, CLEAR

NO_ECHO_MM = 10000
"""Stands for "no echo": farther than the HC-SR04's 4 m range."""


def echo_us_to_mm(pulse_us: int) -> int:
    """Round-trip echo time in microseconds to one-way distance in millimetres (NO_ECHO_MM if invalid)."""
    if pulse_us <= 0:
        return NO_ECHO_MM
    return (pulse_us * 343) // 2000


def median(values: list) -> int:
    """The median of a short list (sorted in place; upper median for even lengths, as on the board)."""
    values.sort()
    return values[len(values) // 2]


def ultrasonic_level(pulses_us: list, threshold_mm: int, caution_mm: int) -> int:
    """BLOCKED when the median distance of the pings is nearer than `threshold_mm`, CAUTION when it is nearer
    than `caution_mm` (0, or not beyond the threshold: no caution band), else CLEAR.

    Turns `pulses_us` into millimetres in place: the board reuses one list every loop, nothing is allocated.
    """
    for i in range(len(pulses_us)):
        pulses_us[i] = echo_us_to_mm(pulses_us[i])
    mm = median(pulses_us)
    if mm < threshold_mm:
        return BLOCKED
    return CAUTION if mm < caution_mm else CLEAR


def digital_occupied(level: int, invert: bool) -> bool:
    """PIR / IR beam level to occupied; `invert` for active-low outputs (most IR beam receivers: 0 = broken)."""
    return (level != 0) != invert
