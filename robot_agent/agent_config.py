"""The robot agent's configuration: which layers it runs, how often it does each piece of work, and tuning.

Three files ship in robot_agent/configs/: `default` (TurtleBot3's stock move_base behaviour, the paper's
baseline), `zones` (default's timings and planner with the zone layer and Algorithm 3: what the sensor network
alone brings) and `full` (zones with event-driven replanning, coarser planning and a smaller, slower local
costmap). The experiment compares them on
the agent's CPU, so each rate here is honoured tick by tick: work not due is not done.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from wsnav.navigation.behaviors.recovery import RecoveryParams
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LAYER_PLUGINS, check_plugins
from wsnav.navigation.costmap.local_costmap import check_local_plugins
from wsnav.navigation.planning.astar import PlannerParams
from wsnav.schemas.yaml_file import read_yaml_mapping

CONFIG_DIR = Path(__file__).parent / "configs"
BUILTIN = ("default", "zones", "full")

Rate = Annotated[float, Field(ge=0, le=1000)]
PositiveRate = Annotated[float, Field(gt=0, le=1000)]


class AgentConfigError(ValueError):
    """A configuration that cannot be used; str() is one line naming the file, the key and the problem."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class InflationSection(_Strict):
    """costmap_2d's inflation_layer; the inscribed radius is the robot's footprint from the site file."""

    inflation_radius: Annotated[float, Field(ge=0, le=10)] = 1.0
    cost_scaling_factor: Annotated[float, Field(ge=0, le=100)] = 3.0

    def params(self, inscribed_radius: float) -> InflationParams:
        return InflationParams(
            inscribed_radius, max(self.inflation_radius, inscribed_radius), self.cost_scaling_factor
        )


class PlannerSection(_Strict):
    """The global planner (NavFn's cost model, see wsnav.navigation.planning.astar)."""

    neutral_cost: Annotated[float, Field(gt=0)] = 50.0
    cost_factor: Annotated[float, Field(ge=0)] = 0.8
    allow_unknown: bool = False
    smooth: bool = True
    downsample: Annotated[int, Field(ge=1, le=4)] = 1
    """Plan on a grid this many times coarser (each coarse cell the highest cost of the cells it covers, so
    never closer to a wall): 3 makes A* ~8x faster on the school map, with the same corridors open and paths
    within a few per cent of the full-resolution length on the sites in sites/."""

    def params(self) -> PlannerParams:
        return PlannerParams(
            neutral_cost=self.neutral_cost,
            cost_factor=self.cost_factor,
            allow_unknown=self.allow_unknown,
            smooth=self.smooth,
        )


class RecoverySection(_Strict):
    """Stock move_base's oscillation detection, patience and recovery behaviours (wsnav.navigation.behaviors.recovery);
    the defaults are ROBOTIS' turtlebot3_navigation move_base_params (noetic)."""

    enabled: bool = False
    oscillation_timeout_s: Annotated[float, Field(ge=0)] = 10.0
    oscillation_distance_m: Annotated[float, Field(ge=0)] = 0.2
    planner_patience_s: Annotated[float, Field(ge=0)] = 5.0
    controller_patience_s: Annotated[float, Field(ge=0)] = 15.0
    conservative_reset_dist_m: Annotated[float, Field(ge=0)] = 3.0
    aggressive_reset_dist_m: Annotated[float, Field(ge=0)] = 0.59
    rotate: bool = True
    on_no_path: bool = True
    """Planner patience starts recoveries when no path is found (stock); false: wait for a zone to change
    (Algorithm 3)."""

    def params(self) -> RecoveryParams | None:
        if not self.enabled:
            return None
        return RecoveryParams(
            oscillation_timeout_s=self.oscillation_timeout_s,
            oscillation_distance_m=self.oscillation_distance_m,
            planner_patience_s=self.planner_patience_s,
            controller_patience_s=self.controller_patience_s,
            conservative_reset_dist_m=self.conservative_reset_dist_m,
            aggressive_reset_dist_m=self.aggressive_reset_dist_m,
            rotate=self.rotate,
            on_no_path=self.on_no_path,
        )


class AgentConfig(_Strict):
    name: str = "custom"
    plugins: list[str] | None = None
    """The costmap's layers by name, in the order they are called (Nav2's costmap `plugins`; the names:
    navigation.costmap.layered_costmap.LAYER_PLUGINS). Unset: the layers `zone_layer`, `obstacle_layer` and
    `fleet_layer` ask for; set, it decides `zone_layer` and `obstacle_layer`."""
    zone_layer: bool = True
    """Subscribe to the sensor network and keep a zone layer in the costmap (the paper's contribution)."""
    obstacle_layer: bool = True
    """Mark what the lidar sees in the costmap (costmap_2d's obstacle layer)."""
    replan_rate_hz: Rate = 0.0
    """Replan the global path at this fixed rate while navigating; 0 = only on events (zone change, controller
    blocked). Stock TurtleBot3 move_base: planner_frequency 5."""
    global_costmap_rate_hz: PositiveRate = 10.0
    """How often the lidar's newest sweep is folded into the costmap (costmap update_frequency)."""
    zone_refresh_rate_hz: PositiveRate = 1.0
    """How often zone freshness is re-judged (a node gone silent turns stale without any message)."""
    local_costmap_size_m: Annotated[float, Field(gt=0.5, le=20)] = 3.0
    """Side of the square window the controller looks at (stock local_costmap width/height: 3 x 3 m)."""
    local_costmap_rate_hz: PositiveRate = 10.0
    """How often the local costmap is updated (local_costmap update_frequency; stock 10)."""
    local_plugins: list[str] | None = None
    """The local costmap's layers by name, in order (move_base's local_costmap `plugins`; the names:
    navigation.costmap.local_costmap.LOCAL_PLUGINS): a rolling window of `local_costmap_size_m` with its own
    obstacle layer, updated at `local_costmap_rate_hz`. Unset: no local costmap of its own, the controller reads
    a window of the global costmap at every control tick."""
    controller_rate_hz: PositiveRate = 10.0
    status_rate_hz: PositiveRate = 2.0
    waiting_retry_s: Annotated[float, Field(ge=0)] = 2.0
    """While waiting for a way, also retry planning this often (0: only when a zone changes)."""
    blocked_replan_interval_s: Annotated[float, Field(gt=0)] = 0.5
    """At most one replan per this interval when the controller reports the path blocked."""
    zone_replan_interval_s: Annotated[float, Field(ge=0, le=60)] = 0.5
    """At most one replan for zone changes per this interval (a flapping node cannot make the robot replan
    without end); the changes in between are planned for at its end, and a goal that became blocked is
    cancelled at once."""
    fleet_layer: bool = True
    """On a site with several robots: the others' published poses as a costmap layer, and the right-of-way rule
    (wsnav.navigation.behaviors.right_of_way). A site with one robot has neither."""
    robot_pose_timeout_s: Annotated[float, Field(gt=0, le=60)] = 2.0
    """Another robot's pose is forgotten this long after its status was made (statuses come at 2 Hz)."""
    yield_distance_m: Annotated[float, Field(ge=0, le=20)] = 1.5
    """Yield to a robot with right of way coming this way within this distance (0: never yield)."""
    max_yield_s: Annotated[float, Field(gt=0, le=3600)] = 30.0
    """Yield to one robot at most this long; after that it is an obstacle to plan round, not a right of way (a
    stolen robot credential claiming `navigating` in front of a robot stopped it for as long as it liked)."""
    max_robot_speed_mps: Annotated[float, Field(gt=0, le=20)] = 2.0
    """Another robot's pose that moved faster than this since its last status is not believed (dropped)."""
    inflation: InflationSection = InflationSection()
    planner: PlannerSection = PlannerSection()
    recovery: RecoverySection = RecoverySection()

    @model_validator(mode="before")
    @classmethod
    def _layers_from_plugins(cls, data: object) -> object:
        """A `plugins` list decides `zone_layer` and `obstacle_layer`; either given too must agree with it."""
        if not isinstance(data, dict) or not isinstance(data.get("plugins"), list):
            return data
        data = dict(data)
        for key in ("zone_layer", "obstacle_layer"):
            named = key in data["plugins"]
            if key in data and data[key] is not named:
                raise ValueError(f"{key}: {data[key]} but plugins {'name' if named else 'leave out'} {key}")
            data[key] = named
        return data

    @field_validator("plugins")
    @classmethod
    def _known_plugins(cls, plugins: list[str] | None) -> list[str] | None:
        if plugins is not None:
            check_plugins(plugins)
        return plugins

    @field_validator("local_plugins")
    @classmethod
    def _known_local_plugins(cls, plugins: list[str] | None) -> list[str] | None:
        if plugins is not None:
            check_local_plugins(plugins)
        return plugins

    def layer_plugins(self) -> list[str]:
        """The costmap's layers by name, in order: `plugins`, or what the layer switches ask for."""
        if self.plugins is not None:
            return list(self.plugins)
        wanted = (True, self.obstacle_layer, self.zone_layer, self.fleet_layer, True)
        return [name for name, on in zip(LAYER_PLUGINS, wanted, strict=True) if on]


def load_agent_config(location: str | Path) -> AgentConfig:
    """A built-in configuration by name (`default`, `zones`, `full`) or a YAML file; raises AgentConfigError (one line)."""
    path = CONFIG_DIR / f"{location}.yaml" if str(location) in BUILTIN else Path(location)
    raw = read_yaml_mapping(
        path, AgentConfigError, "an agent config", f"no such agent config (built in: {', '.join(BUILTIN)})"
    )
    raw.setdefault("name", path.stem)
    try:
        return AgentConfig.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"]) or "config"
        raise AgentConfigError(f"{path}: {key}: {err['msg']}") from None
