"""The zone grid's encoding, checked against costmap_2d's StaticLayer as transcribed from its C++ (no ROS needed)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import SITES
from tests.costmap2d_model import LETHAL, NO_INFORMATION, StaticLayerModel, interpret_value
from wsnav.navigation.costmap.inflation import static_layer
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.ros_bridge.zone_grid import UnrepresentableCost, UpdateWindow, ZoneGridCodec
from wsnav.runtime.bus import Message
from wsnav.schemas import topics
from wsnav.schemas.messages import OperatorBlock, ZoneState
from wsnav.schemas.site import Site, load_site
from wsnav.zones.geometry import Bounds, GridFrame


def test_every_cost_the_zone_layer_makes_comes_back_out_of_the_static_layer() -> None:
    codec = ZoneGridCodec()
    costs = [0, LETHAL, NO_INFORMATION, 200, 127, 50, 251]
    values = codec.encode(np.array(costs, dtype=np.uint8))
    assert [interpret_value(int(v)) for v in values] == costs
    assert (
        values[0] == 0 and values[1] == 100 and values[2] == -1
    )  # clear, lethal, unknown as ROS users expect


def test_a_caution_cost_no_value_maps_onto_is_refused_with_the_nearest_that_work() -> None:
    codec = ZoneGridCodec()
    with pytest.raises(UnrepresentableCost, match=r"zone cost 1 \(nearest that work: 0 or 2\)"):
        codec.check({1, 200})
    representable = [c for c in range(1, 254) if c in {interpret_value(v) for v in range(100)}]
    assert len(representable) == 99
    codec.check(set(representable))


def test_two_updates_between_costmap_cycles_both_reach_the_master() -> None:
    """costmap_2d keeps only the last update's bounds: without the hold, the first change never reaches the master."""
    h, w = 20, 30
    walls = np.zeros((h, w), dtype=np.uint8)
    walls[0, :] = LETHAL
    zones = np.zeros((h, w), dtype=np.uint8)
    codec = ZoneGridCodec()

    def run(hold_s: float) -> np.ndarray:
        layer, master = StaticLayerModel(), walls.copy()
        layer.incoming_map(w, h, codec.encode(zones).ravel().tolist())
        layer.update_master_with_max(master, walls)
        window = UpdateWindow(hold_s)
        costs = zones.copy()
        for t, area in [(0.0, Bounds(2, 2, 5, 6)), (0.1, Bounds(10, 20, 14, 25))]:
            costs[area.rows, area.cols] = LETHAL
            sent = window.add([area], t)
            assert sent is not None
            data = codec.encode(costs[sent.rows, sent.cols]).ravel().tolist()
            layer.incoming_update(sent.col0, sent.row0, sent.shape[1], sent.shape[0], data)
        layer.update_master_with_max(master, walls)  # one cycle after both updates
        return master

    expected = walls.copy()
    expected[2:5, 2:6] = LETHAL
    expected[10:14, 20:25] = LETHAL
    assert np.array_equal(run(hold_s=1.0), expected)
    assert not np.array_equal(run(hold_s=0.0), expected)  # what a plain per-change update would lose


def test_walls_stay_walls_and_unknown_zones_change_nothing_in_the_master() -> None:
    walls = np.zeros((4, 4), dtype=np.uint8)
    walls[0, 0] = LETHAL
    zones = np.full((4, 4), NO_INFORMATION, dtype=np.uint8)
    zones[3, 3] = 0
    zones[2, 2] = 200
    layer, master = StaticLayerModel(), walls.copy()
    layer.incoming_map(4, 4, ZoneGridCodec().encode(zones).ravel().tolist())
    layer.update_master_with_max(master, walls)
    assert master[0, 0] == LETHAL and master[2, 2] == 200 and master[3, 3] == 0 and master[1, 1] == 0


def _school_feed() -> tuple[Site, ZoneFeed]:
    site = load_site(SITES / "school")
    grid = site.grid
    return site, ZoneFeed(
        site.spec, GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])
    )


def test_the_zone_grid_leaves_the_maps_unknown_space_unknown_in_the_master() -> None:
    """Outside every zone the grid says -1 (no information): with updateWithMax a 0 there would turn the map's
    unknown cells (the school's surroundings) into free space in move_base's master, where a planner that keeps
    out of unknown space would then plan."""
    site = load_site(SITES / "school")
    grid = site.grid
    feed = ZoneFeed(
        site.spec, GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])
    )
    walls = static_layer(grid)
    layer, master = StaticLayerModel(), walls.copy()
    layer.incoming_map(grid.width, grid.height, ZoneGridCodec().encode(feed.costs).ravel().tolist())
    layer.update_master_with_max(master, walls)
    unknown = walls == NO_INFORMATION
    assert unknown.any()
    assert np.array_equal(master[unknown], walls[unknown]), "the map's unknown space stays unknown"
    assert np.array_equal(master, walls), "no zone is blocked yet: the master is the map"


def test_a_lifted_block_outside_the_zones_is_a_way_that_may_open() -> None:
    """Lifted, an operator block outside every zone goes back to no information (nothing added to the master):
    the supervisor must hear that a way may have opened, so move_base replans through it."""
    site, feed = _school_feed()
    topic = topics.operator_block(site.name, "b1")
    block = OperatorBlock(polygon=[(30.0, 6.5), (32.0, 6.5), (32.0, 7.5), (30.0, 7.5)])
    placed = feed.take([Message(topic, block.to_payload(), True, 1.0)], 1.0)
    assert placed and not any(c.cheaper for c in placed)
    lifted = feed.take([Message(topic, b"", True, 2.0)], 2.0)
    assert lifted and any(c.cheaper for c in lifted)


def test_a_map_that_differs_from_the_site_by_any_amount_is_refused() -> None:
    """costmap_2d compares /map's metadata with `!=` and, on a difference, resizes and wipes its static layer:
    the bridge allowed half a cell of origin error, which put a master costmap with no walls under move_base."""
    from types import SimpleNamespace

    from wsnav.ros_bridge.bridge_node import map_mismatch
    from wsnav.zones.geometry import GridFrame

    frame = GridFrame(200, 100, 0.05, -10.0, -5.0)

    def info(
        width: int = 200, resolution: float = 0.05, x: float = -10.0, y: float = -5.0
    ) -> SimpleNamespace:
        return SimpleNamespace(
            width=width,
            height=100,
            resolution=resolution,
            origin=SimpleNamespace(position=SimpleNamespace(x=x, y=y)),
        )

    assert map_mismatch(frame, info()) is None
    assert map_mismatch(frame, info(resolution=float(np.float32(0.05)))) is None  # as the wire carries it
    assert (
        map_mismatch(frame, info(x=-10.0 + 0.0125)) == "origin (-9.9875, -5.0), the site's is (-10.0, -5.0)"
    )
    assert map_mismatch(frame, info(y=-5.0 - 1e-9)) is not None
    assert map_mismatch(frame, info(resolution=0.051)) is not None
    assert map_mismatch(frame, info(width=201)) == "size 201x100 cells, the site's is 200x100"


def test_the_zone_grid_keeps_the_walls_where_a_grid_a_fraction_of_a_cell_off_would_wipe_them() -> None:
    """The transcription's resize rule: the bridge's grid carries the site map's metadata exactly, so the map's
    walls survive it; a grid whose origin were off by a quarter cell (what the old check let through) resizes
    the master and wipes them. Also: the costmap waits for the zone grid's first map, and first_map_only would
    drop a restarted bridge's grid."""
    from tests.costmap2d_model import LayeredModel, MapMeta
    from wsnav.schemas.ros_map import FREE

    site, feed = _school_feed()
    grid = site.grid
    frame = GridFrame.of_grid(grid)
    meta = MapMeta(
        frame.width, frame.height, float(np.float32(frame.resolution)), frame.origin_x, frame.origin_y
    )
    walls = [0 if v == FREE else 100 for v in np.flipud(grid.data).ravel()]
    zones = ZoneGridCodec().encode(feed.costs).ravel().tolist()
    for offset, wiped in ((0.0, False), (frame.resolution / 4, True)):
        model = LayeredModel()
        model.add_layer("map")
        model.add_layer("zones")
        model.incoming_map("map", meta, walls)
        assert not model.initialized, "move_base waits for the zone grid's first map"
        shifted = MapMeta(meta.width, meta.height, meta.resolution, meta.origin_x + offset, meta.origin_y)
        model.incoming_map("zones", shifted, zones)
        assert model.initialized
        map_layer = model.layers["map"].costmap
        assert map_layer is not None
        assert bool((map_layer == LETHAL).any()) is not wiped
    model = LayeredModel()
    model.add_layer("zones", first_map_only=True)
    assert model.incoming_map("zones", meta, zones)
    assert not model.incoming_map("zones", meta, zones), "a restarted bridge's grid is never read"


def test_a_clear_zone_is_0_on_the_first_grid_not_only_after_a_change() -> None:
    """docs/ros.md: a clear zone is 0 on the grid. The layer starts every zone clear, so a zone reported clear
    changes nothing in it; the first grid (what a StaticLayer or KeepoutFilter gets first) must already say 0
    there, and -1 only outside the zones."""
    site, feed = _school_feed()
    zone = site.spec.zones[0]
    node = next(n for n in site.spec.nodes if n.zone == zone.id)
    topic = topics.zone_state(site.name, zone.id, node.id)
    payload = ZoneState(zone=zone.id, node=node.id, state="clear", seq=1).to_payload()
    feed.take([Message(topic, payload, True, 1.0)], 1.0)
    grid = ZoneGridCodec().encode(feed.costs)
    window = feed.layer.paint(Bounds(0, 0, feed.frame.height, feed.frame.width), outside=255) != 255
    assert window.any()
    assert set(np.unique(grid[window]).tolist()) == {0}, "every zone cell of a clear school reads 0"
    assert set(np.unique(grid[~window]).tolist()) == {-1}, "outside the zones: no information"
