"""move_base's global costmap parameters, checked the way costmap_2d (noetic) reads them, before the bridge relies
on them.

The zone grid only reaches move_base's plans through a StaticLayer of the global costmap that reads it with the
right parameters, and costmap_2d accepts a wrong set-up in silence:
- without `plugins`, Costmap2DROS builds its pre-Hydro set (map, obstacles, inflation) and the zone grid is in
  none of it;
- with `plugins`, `copyParentParameters` copies the costmap root's `map_topic`, `unknown_cost_value`,
  `lethal_cost_threshold` and `track_unknown_space` into *every* StaticLayer, over the layer's own values, while
  the root's `observation_sources` (ROBOTIS' pre-Hydro TurtleBot3 files keep it there) is not copied: the obstacle
  layer then reads no sensor at all;
- a zone layer without `use_maximum: true` overwrites the master (walls vanish under every clear zone), with
  `trinary_costmap` (the default) caution costs become free or lethal, with a `lethal_cost_threshold` under 100
  caution costs become lethal, without `subscribe_to_updates` no zone change after the first grid arrives, and
  with `first_map_only` a restarted bridge's grid is never read;
- a StaticLayer of the map placed after the zone layer overwrites the zones.
`check_global_costmap` says each of these in a few words; the bridge refuses to start on any of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

STATIC = "costmap_2d::StaticLayer"
OBSTACLES = ("costmap_2d::ObstacleLayer", "costmap_2d::VoxelLayer")
INFLATION = "costmap_2d::InflationLayer"
COPIED_TO_STATIC = ("map_topic", "unknown_cost_value", "lethal_cost_threshold", "track_unknown_space")
"""costmap_2d_ros.cpp copyParentParameters: the root's values of these replace each StaticLayer's."""
STATIC_DEFAULTS: dict[str, Any] = {
    "map_topic": "map",
    "first_map_only": False,
    "subscribe_to_updates": False,
    "track_unknown_space": True,
    "use_maximum": False,
    "lethal_cost_threshold": 100,
    "unknown_cost_value": -1,
    "trinary_costmap": True,
}
"""static_layer.cpp onInitialize."""


@dataclass
class CostmapCheck:
    """What is wrong (the bridge refuses) and what is only worth a warning."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    zone_layer: str | None = None


def _global(topic: str, namespace: str = "/") -> str:
    """A topic name as costmap_2d's global NodeHandle resolves it (relative names under move_base's namespace)."""
    return topic if topic.startswith("/") else namespace.rstrip("/") + "/" + topic


def static_param(costmap: dict[str, Any], layer: str, key: str) -> Any:
    """The value a StaticLayer named `layer` ends up with for `key`."""
    if key in COPIED_TO_STATIC and key in costmap:
        return costmap[key]
    own = costmap.get(layer)
    if isinstance(own, dict) and key in own:
        return own[key]
    return STATIC_DEFAULTS[key]


def check_global_costmap(costmap: dict[str, Any], zone_topic: str, namespace: str = "/") -> CostmapCheck:
    """`costmap` is the parameter dictionary of move_base's `global_costmap` (rospy.get_param)."""
    check = CostmapCheck()
    plugins = costmap.get("plugins")
    if not isinstance(plugins, list):
        check.errors.append(
            "the global costmap has no `plugins` list: costmap_2d builds its pre-Hydro layers (map, obstacles, "
            f"inflation) and none reads {zone_topic}"
        )
        return check
    layers = [(str(p.get("name")), str(p.get("type"))) for p in plugins if isinstance(p, dict)]
    if "map_topic" in costmap:
        check.errors.append(
            f"global_costmap/map_topic ({costmap['map_topic']}) is set at the costmap's root: costmap_2d copies it "
            "into every StaticLayer, the zone layer included; put it under the map's layer (static_layer/map_topic)"
        )
    statics = [(i, name) for i, (name, kind) in enumerate(layers) if kind == STATIC]
    zone = [
        (i, n)
        for i, n in statics
        if _global(str(static_param(costmap, n, "map_topic")), namespace) == zone_topic
    ]
    if not zone:
        check.errors.append(
            f"no StaticLayer of the global costmap reads {zone_topic} (plugins: {_names(layers)})"
        )
        return check
    index, name = zone[0]
    check.zone_layer = name

    def value(key: str) -> Any:
        return static_param(costmap, name, key)

    if value("use_maximum") is not True:
        check.errors.append(f"{name}: use_maximum must be true (else the zone layer overwrites the walls)")
    if value("trinary_costmap") is not False:
        check.errors.append(
            f"{name}: trinary_costmap must be false (else caution costs become free or lethal)"
        )
    if value("lethal_cost_threshold") != 100:
        check.errors.append(f"{name}: lethal_cost_threshold must be 100 (else caution costs become lethal)")
    if value("first_map_only") is not False:
        check.errors.append(
            f"{name}: first_map_only must be false (else a restarted bridge's grid is never read)"
        )
    if value("subscribe_to_updates") is not True:
        check.errors.append(
            f"{name}: subscribe_to_updates must be true (else no zone change after the first grid)"
        )
    for other, other_name in statics:
        if other > index:
            check.errors.append(
                f"{other_name} (a StaticLayer after {name}) overwrites the zones: list {name} after it"
            )
    inflation = [i for i, (_, kind) in enumerate(layers) if kind == INFLATION]
    if inflation and index > inflation[0]:
        check.warnings.append(f"{name} comes after the inflation layer: zones are not inflated like walls")
    for layer, kind in layers:
        own = costmap.get(layer)
        sources = own.get("observation_sources") if isinstance(own, dict) else None
        if kind in OBSTACLES and not sources and costmap.get("observation_sources"):
            check.errors.append(
                f"{layer} reads no sensor: with `plugins` set, costmap_2d ignores the root's observation_sources "
                f"({costmap['observation_sources']}); put it and its sources under {layer}/"
            )
    return check


def _names(layers: list[tuple[str, str]]) -> str:
    return ", ".join(name for name, _ in layers) or "none"
