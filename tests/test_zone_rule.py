"""The zone layer's policy: states to costs, staleness by message age, offline nodes, fusion of the two nodes
watching z1 and z4 on the school site, and operator blocks that expire or are removed."""

from __future__ import annotations

import pytest

from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site import Site
from wsnav.schemas.site_file import ZonePolicy
from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import ZoneRule

HEARTBEAT = 5.0  # the school's heartbeat_s
STALE_AFTER = 3 * HEARTBEAT


def layer_for(site: Site, **policy: object) -> ZoneRule:
    return ZoneRule(
        site.spec, GridFrame.of_grid(site.grid), ZonePolicy.model_validate(policy) if policy else None
    )


class Feed:
    """Sends zone states with increasing seq, as a node would."""

    def __init__(self, layer: ZoneRule) -> None:
        self.layer = layer
        self.seq = 0

    def __call__(self, zone: str, node: str, state: str, t: float) -> bool:
        self.seq += 1
        return self.layer.on_zone_state(
            ZoneState.model_validate({"zone": zone, "node": node, "state": state, "seq": self.seq}), t
        )


def test_states_map_to_costmap_costs(school: Site) -> None:
    layer = layer_for(school, caution_cost=120)
    feed = Feed(layer)
    assert layer.zone_costs() == dict.fromkeys([f"z{i}" for i in range(1, 8)], FREE_SPACE)
    assert feed("z2", "n3", "blocked", 0.0) is True
    assert feed("z3", "n4", "caution", 0.0) is True
    assert layer.zone_costs()["z2"] == LETHAL_OBSTACLE
    assert layer.zone_costs()["z3"] == 120
    assert layer.blocked_zones() == ["z2"]
    assert feed("z2", "n3", "blocked", 1.0) is False, "a heartbeat with the same word changes nothing"
    assert feed("z2", "n3", "clear", 2.0) is True
    assert layer.blocked_zones() == []
    assert layer.take_changes(), "the changed zones' windows are handed to the costmap"
    assert layer.take_changes() == []


@pytest.mark.parametrize(
    ("stale", "cost"),
    [("keep", 200), ("unknown", NO_INFORMATION), ("lethal", LETHAL_OBSTACLE)],
)
def test_a_silent_node_goes_stale_after_three_heartbeats(school: Site, stale: str, cost: int) -> None:
    layer = layer_for(school, stale=stale)
    feed = Feed(layer)
    feed("z7", "n9", "blocked", 100.0)
    feed("z7", "n9", "caution" if stale == "keep" else "clear", 103.0)
    fresh = layer.zone_costs()["z7"]
    layer.refresh(103.0 + STALE_AFTER)
    assert layer.zone_costs()["z7"] == fresh, "exactly three heartbeats old is still fresh"
    layer.refresh(103.0 + STALE_AFTER + 0.1)
    assert layer.zone_costs()["z7"] == cost
    # A fresh message ends the staleness at once.
    feed("z7", "n9", "clear", 200.0)
    assert layer.zone_costs()["z7"] == FREE_SPACE


def test_a_node_never_heard_from_goes_stale_counted_from_the_layer_start(school: Site) -> None:
    layer = layer_for(school, stale="lethal")
    layer.refresh(0.0)
    assert layer.blocked_zones() == []
    Feed(layer)("z1", "n1", "clear", 10.0)
    Feed(layer)("z1", "n2", "clear", 10.0)
    assert layer.refresh(STALE_AFTER + 1.0) is True
    assert "z1" not in layer.blocked_zones(), "z1's nodes spoke at t=10"
    assert {"z2", "z3", "z4", "z5", "z6", "z7"} <= set(layer.blocked_zones())


def test_a_per_node_heartbeat_override_sets_its_stale_time(school: Site) -> None:
    spec = school.spec.model_copy(
        update={
            "nodes": [
                n.model_copy(update={"heartbeat_s": 1.0}) if n.id == "n3" else n for n in school.spec.nodes
            ]
        }
    )
    layer = ZoneRule(spec, GridFrame.of_grid(school.grid), ZonePolicy(stale="unknown"))
    feed = Feed(layer)
    feed("z2", "n3", "clear", 0.0)
    feed("z3", "n4", "clear", 0.0)
    layer.refresh(4.0)
    assert layer.zone_costs()["z2"] == NO_INFORMATION
    assert layer.zone_costs()["z3"] == FREE_SPACE


@pytest.mark.parametrize(
    ("stale", "cost"), [("keep", FREE_SPACE), ("unknown", NO_INFORMATION), ("lethal", LETHAL_OBSTACLE)]
)
def test_an_offline_node_is_stale_at_once_and_its_birth_and_state_restore_it(
    school: Site, stale: str, cost: int
) -> None:
    layer = layer_for(school, stale=stale)
    feed = Feed(layer)
    feed("z5", "n7", "clear", 0.0)
    assert layer.on_node_status(NodeStatus(node="n7", status="offline"), 1.0) is (stale != "keep")
    assert layer.zone_costs()["z5"] == cost
    layer.on_node_status(NodeStatus(node="n7", status="online"), 2.0)
    assert layer.zone_costs()["z5"] == FREE_SPACE


def test_any_blocked_fusion_lets_one_fresh_blocked_win_in_z1_and_z4(school: Site) -> None:
    layer = layer_for(school, stale="unknown")
    feed = Feed(layer)
    feed("z1", "n1", "clear", 0.0)
    feed("z1", "n2", "blocked", 0.0)
    assert layer.blocked_zones() == ["z1"]
    feed("z4", "n5", "caution", 0.0)
    feed("z4", "n6", "clear", 0.0)
    assert layer.zone_costs()["z4"] == 200, "the worst word of the two nodes"
    # n6 goes silent: unknown beats caution, a fresh blocked beats unknown.
    feed("z4", "n5", "caution", 14.0)
    layer.refresh(16.0)
    assert layer.zone_costs()["z4"] == NO_INFORMATION
    feed("z4", "n5", "blocked", 17.0)
    assert layer.blocked_zones() == ["z4"]
    assert layer.zone_costs()["z1"] == NO_INFORMATION, "z1's blocked report went stale: unknown"


def test_majority_fusion_needs_more_than_half_of_the_nodes(school: Site) -> None:
    layer = layer_for(school, fuse="majority", caution_cost=99)
    feed = Feed(layer)
    feed("z1", "n1", "blocked", 0.0)
    feed("z1", "n2", "clear", 0.0)
    assert layer.zone_costs()["z1"] == 99, "one of two says blocked: caution, not lethal"
    feed("z1", "n2", "blocked", 1.0)
    assert layer.blocked_zones() == ["z1"]
    feed("z2", "n3", "blocked", 1.0)
    assert "z2" in layer.blocked_zones(), "a zone with one node follows it"


def test_operator_zone_block_holds_until_it_expires(school: Site) -> None:
    layer = layer_for(school)
    feed = Feed(layer)
    feed("z6", "n8", "clear", 0.0)
    assert layer.on_operator_block(
        "forklift", OperatorBlock(zone="z6", expires_at=60.0, reason="forklift"), 1.0
    )
    assert layer.blocked_zones() == ["z6"]
    feed("z6", "n8", "clear", 30.0)
    assert layer.blocked_zones() == ["z6"], "the node's clear does not lift an operator block"
    assert layer.refresh(59.9) is False
    assert layer.refresh(60.0) is True
    assert layer.blocked_zones() == []
    assert layer.active_blocks() == []


def test_operator_polygon_block_is_painted_and_removed_by_an_empty_payload(school: Site) -> None:
    layer = layer_for(school)
    square = [(30.0, 22.0), (31.0, 22.0), (31.0, 23.0), (30.0, 23.0)]
    assert layer.on_operator_block("spill", OperatorBlock(polygon=square), 0.0)
    assert layer.blocked_zones() == [], "a polygon block is not a zone"
    assert layer.active_blocks() == ["spill"]
    window = layer.block_window("spill")
    assert window is not None
    painted = layer.paint(layer.take_changes()[0])
    assert painted.max() == LETHAL_OBSTACLE and int((painted == LETHAL_OBSTACLE).sum()) == int(
        window.mask.sum()
    )
    assert layer.on_operator_block("spill", None, 5.0)
    changes = layer.take_changes()
    assert changes and layer.paint(changes[0]).max() == FREE_SPACE
    assert layer.on_operator_block("spill", None, 6.0) is False, "removing twice changes nothing"


def test_a_block_that_already_expired_or_names_no_zone_changes_nothing(school: Site) -> None:
    layer = layer_for(school)
    layer.refresh(100.0)
    assert layer.on_operator_block("late", OperatorBlock(zone="z1", expires_at=50.0), 100.0) is False
    assert layer.on_operator_block("ghost", OperatorBlock(zone="nope"), 100.0) is False
    assert layer.blocked_zones() == []
