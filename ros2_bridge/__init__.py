"""wsnav on ROS 2: the zone layer as a nav_msgs/msg/OccupancyGrid (and its nav2_msgs/msg/CostmapFilterInfo) for
Nav2's StaticLayer or KeepoutFilter, written on DDS with Cyclone DDS as ROS 2 itself would, so no ROS 2 install is
needed on the machine that runs it. The MQTT side and the grid's values are the ROS 1 bridge's (ros_bridge)."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package (messages needs cyclonedds)
    from wsnav.ros2_bridge import bridge, cli, messages

__all__ = ["bridge", "cli", "messages"]
