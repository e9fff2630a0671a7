"""The firmware's own pure logic modules, imported by their board names (the same source files the ESP8266 runs).

One place does the import for the rest of zone_sim; see firmware/__init__.py for why the device
folder goes on sys.path.
"""

from __future__ import annotations

import importlib
from typing import Any

import firmware

firmware.add_device_path()
# By name at run time: the device folder is not a package, so the type checker cannot follow these imports.
backoff: Any = importlib.import_module("backoff")
diagnostics: Any = importlib.import_module("diagnostics")
node_logic: Any = importlib.import_module("node_logic")
nodeconfig: Any = importlib.import_module("nodeconfig")
payloads: Any = importlib.import_module("payloads")
sensing: Any = importlib.import_module("sensing")

Backoff = backoff.Backoff
POWER_ON_RESET = 0
"""`machine.reset_cause()` after a power cycle, the only way an emulated node restarts."""
NodeLogic = node_logic.NodeLogic
ConfigError = nodeconfig.ConfigError
parse_node_config = nodeconfig.parse
digital_occupied = sensing.digital_occupied
BLOCKED_LEVEL = importlib.import_module("debounce").BLOCKED


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
