"""The firmware's own pure logic modules (the same source files the ESP8266 runs).

One place does the import for the rest of zone_sim; see firmware/__init__.py for how the board's module names
are kept out of the top level.
"""

from __future__ import annotations

from typing import Any

from wsnav.firmware import PURE_MODULES, load_device_modules

# Loaded at run time: the device folder is not a package, so the type checker cannot follow these imports.
_device: dict[str, Any] = load_device_modules(*PURE_MODULES)
backoff: Any = _device["backoff"]
diagnostics: Any = _device["diagnostics"]
node_logic: Any = _device["node_logic"]
nodeconfig: Any = _device["nodeconfig"]
payloads: Any = _device["payloads"]
sensing: Any = _device["sensing"]

Backoff = backoff.Backoff
POWER_ON_RESET = 0
"""`machine.reset_cause()` after a power cycle, the only way an emulated node restarts."""
NodeLogic = node_logic.NodeLogic
ConfigError = nodeconfig.ConfigError
parse_node_config = nodeconfig.parse
digital_occupied = sensing.digital_occupied
BLOCKED_LEVEL = _device["debounce"].BLOCKED


def ultrasonic_occupied(pulses_us: list[int], threshold_mm: int) -> bool:
    """Occupied when the median distance of the pings is nearer than the threshold: the firmware's
    `ultrasonic_level` without a caution band (the board keeps no separate function for it: heap)."""
    return bool(sensing.ultrasonic_level(pulses_us, threshold_mm, 0) == BLOCKED_LEVEL)


NO_ECHO_MM = sensing.NO_ECHO_MM
SEQ_BASE_BITS = 20
"""app.py seeds a node's seq with `random.getrandbits(20)` at every boot."""

__all__ = [
    "NO_ECHO_MM",
    "POWER_ON_RESET",
    "SEQ_BASE_BITS",
    "Backoff",
    "ConfigError",
    "NodeLogic",
    "diagnostics",
    "digital_occupied",
    "parse_node_config",
    "payloads",
    "ultrasonic_occupied",
]
