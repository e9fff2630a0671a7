"""The plan a robot's status carries: from the point nearest the robot to the goal, within the message's point
budget, in centimetres (what an operator's map draws ahead of the robot)."""

from __future__ import annotations

import numpy as np

from wsnav.robot_agent.agent import path_ahead
from wsnav.schemas.messages import ROBOT_PATH_POINTS


def test_a_short_plan_goes_out_whole_from_the_vertex_nearest_the_robot() -> None:
    path = np.array([[0.0, 0.0], [2.0, 0.004], [2.0, 3.0], [5.126, 3.0]])
    assert path_ahead(path, 1.9, 0.5) == [(2.0, 0.0), (2.0, 3.0), (5.13, 3.0)]
    assert path_ahead(np.zeros((0, 2)), 0.0, 0.0) is None


def test_a_long_plan_is_thinned_evenly_to_the_budget_keeping_both_ends() -> None:
    for n in (ROBOT_PATH_POINTS + 1, 100):
        path = np.zeros((n, 2), dtype=np.float64)
        path[:, 0] = np.arange(n) * 0.1
        sent = path_ahead(path, 0.0, 0.0)
        assert sent is not None and len(sent) == ROBOT_PATH_POINTS
        assert sent[0] == (0.0, 0.0) and sent[-1] == (round((n - 1) * 0.1, 2), 0.0)
        gaps = np.diff([x for x, _ in sent])
        assert gaps.max() - gaps.min() <= 0.11
