"""What `wsnav ros bridge` was asked to do (its command line, checked): shared by the grid node and the move_base
link."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class BridgeOptions:
    frame_id: str
    namespace: str
    map_topic: str
    map_wait_s: float
    update_hold_s: float
    robot: str | None
    move_base: str
    plan_topic: str
    base_frame: str
    master_costmap: str = "/move_base/global_costmap/costmap"
    relay: str | None = None
    """An action name where the bridge serves MoveBaseAction and relays to move_base (`MoveBaseLink._on_relay_goal`)."""
    state_dir: Path | None = None
    """Where the last known zone states are kept across restarts (`--state-dir`), or None."""
