"""The zone-node firmware (device/, MicroPython) and its host-side tooling (build, deploy, flash, testing).

The pure logic modules of device/ run unchanged under CPython (the zone simulator runs them for up to 1000
emulated nodes). They import each other by top-level name, as on the board, so CPython code puts device/ on
sys.path with `add_device_path()` and then imports only the names in PURE_MODULES:

    import firmware
    firmware.add_device_path()
    from node_logic import NodeLogic
"""

from __future__ import annotations

import sys
from pathlib import Path

DEVICE_DIR = Path(__file__).resolve().parent / "device"
PURE_MODULES = ("backoff", "debounce", "diagnostics", "node_logic", "nodeconfig", "payloads", "sensing")
"""No I/O, no machine/network: safe to import on CPython. The rest of device/ needs a board (or host_stubs)."""


def add_device_path() -> None:
    """Make the pure firmware modules importable by their board names (idempotent)."""
    path = str(DEVICE_DIR)
    if path not in sys.path:
        sys.path.append(path)
