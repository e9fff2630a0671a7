"""The zone layer's incremental refresh (only zones whose nodes' staleness deadline passed) gives exactly what
evaluating every zone gives, under each stale policy and fusion, through births, wills, silences, heartbeats and
operator blocks that expire: the console asks it once per message, so it must be cheap and still the one rule."""

from __future__ import annotations

import random

import pytest

from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site import Site
from wsnav.schemas.site_file import ZonePolicy
from wsnav.zones.geometry import GridFrame
from wsnav.zones.zone_rule import ZoneRule


def everything_again(layer: ZoneRule) -> dict[str, str]:
    """What the layer's words would be if every zone were evaluated from scratch now."""
    return {z: layer.zone_word(z) for z in layer._zone_ids}


@pytest.mark.parametrize("stale", ["keep", "unknown", "lethal"])
@pytest.mark.parametrize("fuse", ["any_blocked", "majority"])
def test_incremental_refresh_matches_evaluating_every_zone(school: Site, stale: str, fuse: str) -> None:
    policy = ZonePolicy.model_validate({"stale": stale, "fuse": fuse})
    fast = ZoneRule(school.spec, GridFrame.of_grid(school.grid), policy)
    full = ZoneRule(school.spec, GridFrame.of_grid(school.grid), policy)
    rng = random.Random(f"{stale}-{fuse}")
    nodes = [(n.id, n.zone) for n in school.spec.nodes]
    zones = [z.id for z in school.spec.zones]
    seq = 0
    t = 100.0
    for step in range(3000):
        t += rng.choice([0.1, 0.5, 1.0, 3.0, 7.0])
        roll = rng.random()
        node, zone = rng.choice(nodes)
        if roll < 0.5:
            seq += 1
            state = rng.choice(["clear", "clear", "caution", "blocked"])
            msg = ZoneState.model_validate({"zone": zone, "node": node, "state": state, "seq": seq})
            for layer in (fast, full):
                layer.on_zone_state(msg, t)
        elif roll < 0.6:
            status = NodeStatus.model_validate({"node": node, "status": rng.choice(["online", "offline"])})
            for layer in (fast, full):
                layer.on_node_status(status, t)
        elif roll < 0.65:
            block_id = f"b{rng.randrange(3)}"
            block = (
                OperatorBlock(zone=rng.choice(zones), expires_at=t + rng.uniform(1, 30))
                if rng.random() < 0.7
                else None
            )
            for layer in (fast, full):
                layer.on_operator_block(block_id, block, t)
        fast_changed = fast.refresh(t)
        full._tick(t)
        full_changed = full._reevaluate()  # every zone: the rule as it was before the incremental path
        assert fast.zone_costs() == full.zone_costs(), (step, t)
        assert fast_changed == full_changed, (step, t)
        assert everything_again(fast) == everything_again(full)
        assert [fast.stale_nodes(z) for z in zones] == [full.stale_nodes(z) for z in zones]
