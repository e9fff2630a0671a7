"""The local costmap the controller reads: costmap_2d's rolling window with its own layers, size and update rate
(navigation/costmap/local_costmap.py), the lever the paper turns down in `full`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.robot_agent_rig import DT, Rig, scan_from
from tests.site_fixtures import tiny_site
from wsnav.navigation.costmap.inflation import InflationParams
from wsnav.navigation.costmap.layered_costmap import LayeredCostmap
from wsnav.navigation.costmap.local_costmap import LocalCostmap
from wsnav.robot_agent.agent_config import AgentConfigError, load_agent_config
from wsnav.schemas.site import Site, load_site
from wsnav.zones.cost_values import FREE_SPACE, INSCRIBED_INFLATED_OBSTACLE, LETHAL_OBSTACLE

INFLATION = InflationParams(inscribed_radius=0.105, inflation_radius=1.0, cost_scaling_factor=3.0)


@pytest.fixture
def tiny(tmp_path: Path) -> Site:
    return load_site(tiny_site(tmp_path / "tiny"))


def cost_at(local: LocalCostmap, x: float, y: float) -> int:
    costs, frame = local.window()
    row, col = frame.world_to_cell(x, y)
    assert 0 <= row < frame.height and 0 <= col < frame.width, "the point lies outside the window"
    return int(costs[row, col])


def test_the_local_costmap_sees_the_lidar_in_its_window_and_forgets_what_leaves_it(tiny: Site) -> None:
    """ROBOTIS' local costmap (obstacle and inflation layers, 3 x 3 m rolling window): a lidar hit is marked and
    inflated around the robot; the map's walls are not in it (the global plan keeps the robot off them); driven away until the mark left the window and back with no new scan, the mark
    is gone, as costmap_2d's rolling window forgets it."""
    global_costmap = LayeredCostmap(tiny.grid, INFLATION)
    local = LocalCostmap(global_costmap, 3.0, INFLATION, ["obstacle_layer", "inflation_layer"])
    here = (2.0, 3.5, 0.0)
    local.update(here, scan_from(here, {0: 1.0}))
    costs, frame = local.window()
    assert costs.shape == (60, 60) and frame.resolution == tiny.grid.resolution
    assert cost_at(local, 3.0, 3.5) == LETHAL_OBSTACLE
    assert cost_at(local, 2.95, 3.5) == INSCRIBED_INFLATED_OBSTACLE
    assert (
        global_costmap.cost_at(0.0, 3.5) == LETHAL_OBSTACLE
    )  # the west wall, 0.5 m beyond the window's edge...
    assert cost_at(local, 0.6, 3.5) == FREE_SPACE  # ...and nothing of it inside: no static layer
    local.update((7.0, 3.5, 0.0), None)  # 5 m east: the mark at x 3 is outside the window
    local.update(here, None)
    assert cost_at(local, 3.0, 3.5) == FREE_SPACE, "the mark left the window and was forgotten"


def test_static_layer_in_the_list_brings_the_map_into_the_window_and_a_reset_clears_only_marks(
    tiny: Site,
) -> None:
    global_costmap = LayeredCostmap(tiny.grid, INFLATION)
    local = LocalCostmap(
        global_costmap, 2.0, INFLATION, ["static_layer", "obstacle_layer", "inflation_layer"]
    )
    here = (1.0, 1.0, 0.0)
    local.update(here, scan_from(here, {90: 0.5}))  # a hit 0.5 m north
    costs, _ = local.window()
    assert costs.shape == (40, 40)
    assert cost_at(local, 1.0, 1.5) == LETHAL_OBSTACLE
    wall = np.argwhere(global_costmap.static.costs == LETHAL_OBSTACLE)
    row, col = (int(v) for v in wall[np.argmin(np.hypot(*(wall - [20, 20]).T))])
    x, y = global_costmap.frame.cell_to_world(row, col)
    assert cost_at(local, x, y) == LETHAL_OBSTACLE, "the map's wall is in the window"
    local.clear_except_region(1.0, 1.0, 0.59)  # move_base's aggressive reset
    assert cost_at(local, 1.0, 1.5) < INSCRIBED_INFLATED_OBSTACLE, "the lidar mark outside the square went"
    assert cost_at(local, x, y) == LETHAL_OBSTACLE, "the map is not the robot's to forget"


def test_a_local_costmap_refuses_the_zone_layer_and_unknown_layers_in_one_line(tmp_path: Path) -> None:
    for bad, says in [
        ("local_plugins: [obstacle_layer, zone_layer, inflation_layer]\n", "takes no zone_layer"),
        ("local_plugins: [obstacle_layer, voxel_layer, inflation_layer]\n", "unknown local costmap plugin"),
        ("local_plugins: [obstacle_layer]\n", "lack 'inflation_layer'"),
    ]:
        path = tmp_path / "agent.yaml"
        path.write_text(bad)
        with pytest.raises(AgentConfigError, match=says) as refused:
            load_agent_config(path)
        assert "\n" not in str(refused.value)


def test_default_has_robotis_local_costmap_and_full_the_papers_smaller_slower_one(tmp_path: Path) -> None:
    """The agent updates its local costmap at the configuration's rate and size, which the controller then reads:
    `default` ROBOTIS' 3 x 3 m at 10 Hz, `full` the paper's 2 x 2 m at 5 Hz."""
    seen: dict[str, tuple[int, tuple[int, int]]] = {}
    for config in ("default", "full"):
        with Rig(tmp_path / config, config=config) as rig:
            local = rig.agent.local_costmap
            assert local is not None and local.plugins == [
                "obstacle_layer",
                "robots_layer",
                "inflation_layer",
            ]
            for _ in range(round(2.0 / DT)):  # 2 simulated seconds
                rig.agent.step(rig.clock.now())
                rig.robot.step(DT, rig.clock.now() + DT)
                rig.clock.advance(DT)
            costs, frame = local.window()
            seen[config] = (local.updates, costs.shape)
            x, y, _ = rig.robot.pose()
            assert frame.origin_x < x < frame.origin_x + frame.width * frame.resolution
            assert frame.origin_y < y < frame.origin_y + frame.height * frame.resolution
    assert seen == {"default": (20, (60, 60)), "full": (10, (40, 40))}
