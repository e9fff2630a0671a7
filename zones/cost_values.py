"""costmap_2d's cost values, which every layer and the zone rule speak (users of ROS read costs by them).

0 free, 253 inscribed (the robot's centre here means a collision), 254 lethal, 255 unknown; 1-252 graded.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FREE_SPACE = 0
INSCRIBED_INFLATED_OBSTACLE = 253
LETHAL_OBSTACLE = 254
NO_INFORMATION = 255

Costs = NDArray[np.uint8]
"""A grid of cost values, row 0 the map's bottom row."""

__all__ = ["FREE_SPACE", "INSCRIBED_INFLATED_OBSTACLE", "LETHAL_OBSTACLE", "NO_INFORMATION", "Costs"]
