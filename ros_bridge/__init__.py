"""wsnav on ROS 1: the zone layer as an OccupancyGrid for costmap_2d (and Nav2's KeepoutFilter), Algorithm 3 over
move_base's action topics, and ROS robot backends. rospy comes from Debian's packages (see ros_env)."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.ros_bridge import (
        bridge_node,
        cli,
        move_base_supervisor,
        robot_backend,
        robot_cli,
        ros_env,
        sim_node,
        zone_feed,
        zone_grid,
        zone_source,
    )

__all__ = [
    "bridge_node",
    "cli",
    "move_base_supervisor",
    "robot_backend",
    "robot_cli",
    "ros_env",
    "sim_node",
    "zone_feed",
    "zone_grid",
    "zone_source",
]
