"""wsnav on ROS 1: the zone layer as an OccupancyGrid for costmap_2d (and Nav2's KeepoutFilter), Algorithm 3 over
move_base's action topics, and ROS robot backends. rospy comes from Debian's packages (see ros_env)."""
