"""The zone-node firmware (device/, MicroPython) and its host-side tooling (build, deploy, flash; and, in the
checkout only, not in the wheel, the tests' drivers of the MicroPython unix port: testing.py, unix_board.py).

The pure logic modules of device/ run unchanged under CPython (the zone simulator runs them for up to 1000
emulated nodes). On the board they import each other by top-level name (`from debounce import Debouncer`);
here `load_device_modules` gives them those names only while they load, then keeps them as
`wsnav.firmware.device.<name>`, so no top-level `backoff` or `payloads` shadows (or is shadowed by) a PyPI
package of that name.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.firmware import board, build, cli, deploy

import sys
from collections.abc import Sequence
from importlib import import_module
from pathlib import Path
from types import ModuleType

DEVICE_DIR = Path(__file__).resolve().parent / "device"
PURE_MODULES = ("backoff", "debounce", "diagnostics", "node_logic", "nodeconfig", "payloads", "sensing")
"""No I/O, no machine/network: safe to import on CPython. The rest of device/ needs a board (or host_stubs)."""
DEVICE_PACKAGE = "wsnav.firmware.device"

_loaded: dict[str, ModuleType] = {}


def load_device_modules(*names: str, extra_dirs: Sequence[Path] = ()) -> dict[str, ModuleType]:
    """The named board modules (and those they import), loaded once under `wsnav.firmware.device.`.

    `extra_dirs` adds host-side board scripts (tests' checks) that import device modules by board name."""
    wanted = [n for n in names if n not in _loaded]
    if not wanted:
        return {n: _loaded[n] for n in names}
    dirs = [str(d) for d in (DEVICE_DIR, *extra_dirs)]
    bare = {py.stem for d in dirs for py in Path(d).glob("*.py")}
    shadowed = {n: sys.modules.pop(n) for n in list(bare) if n in sys.modules}
    for n, module in _loaded.items():
        sys.modules[n] = module
    sys.path[:0] = dirs
    try:
        for n in wanted:
            import_module(n)
    finally:
        del sys.path[: len(dirs)]
        for n in bare:
            module = sys.modules.pop(n, None)
            if module is not None and n not in _loaded:
                _rename(module, n)
                _loaded[n] = module
        sys.modules.update(shadowed)
    return {n: _loaded[n] for n in names}


def _rename(module: ModuleType, name: str) -> None:
    """Give a loaded board module (and what it defines) its namespaced name, so pickle and logs find it."""
    qualified = f"{DEVICE_PACKAGE}.{name}"
    module.__name__ = qualified
    sys.modules[qualified] = module
    for value in vars(module).values():
        if getattr(value, "__module__", None) == name:
            try:
                value.__module__ = qualified
            except (AttributeError, TypeError):
                continue


__all__ = [
    "DEVICE_DIR",
    "PURE_MODULES",
    "board",
    "build",
    "cli",
    "deploy",
    "load_device_modules",
]
