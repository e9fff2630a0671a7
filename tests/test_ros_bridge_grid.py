# pyright: reportMissingImports=false
"""`wsnav ros bridge` against a real roscore and the real broker: the zone grid a stock costmap_2d StaticLayer
builds from /wsn/zone_grid and its updates equals wsnav's own zone layer, event after event.

The bridge runs as its own process; the test process is a ROS node that applies OccupancyGrid and
OccupancyGridUpdate as costmap_2d's StaticLayer does (tests/costmap2d_model.py, from the C++), and an MQTT
client per node and for the operator. The reference is a zone layer in the test fed the same messages: the site's
heartbeat is long, so staleness comes only from node wills, and nothing depends on the machine's speed.
"""

from __future__ import annotations

import random
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import require_tool
from tests.costmap2d_model import StaticLayerModel
from tests.ros_fixtures import RosMaster, WsnavChild, bridge_args, slow_heartbeat_school, wait_until
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.ros_bridge.zone_feed import ZoneFeed
from wsnav.runtime.bus import Message
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site import load_site
from wsnav.zones.geometry import GridFrame

EVENTS = 100


@pytest.fixture
def school_broker(tmp_path: Path) -> Iterator[tuple[Path, BrokerThread]]:
    site_dir = slow_heartbeat_school(tmp_path)
    with BrokerThread(site_dir) as broker:
        yield site_dir, broker


class StaticLayerPeer:
    """The test node's subscriber: the zone grid as a stock StaticLayer holds it."""

    def __init__(self, namespace: str = "/wsn") -> None:
        import rospy
        from map_msgs.msg import OccupancyGridUpdate
        from nav_msgs.msg import OccupancyGrid

        self.layer = StaticLayerModel()
        self.grids = 0
        self.latching: str | None = None
        self.update_cells: list[int] = []
        self.size = (0, 0)
        self.lock = threading.Lock()
        self._subs = [
            rospy.Subscriber(f"{namespace}/zone_grid", OccupancyGrid, self._grid, queue_size=2),
            rospy.Subscriber(
                f"{namespace}/zone_grid_updates", OccupancyGridUpdate, self._update, queue_size=50
            ),
        ]

    def _grid(self, msg: Any) -> None:
        with self.lock:
            self.grids += 1
            self.latching = msg._connection_header.get("latching")
            self.size = (msg.info.width, msg.info.height)
            self.layer.incoming_map(msg.info.width, msg.info.height, msg.data)

    def _update(self, msg: Any) -> None:
        with self.lock:
            self.update_cells.append(msg.width * msg.height)
            self.layer.incoming_update(msg.x, msg.y, msg.width, msg.height, msg.data)

    def grid(self) -> np.ndarray | None:
        with self.lock:
            return None if self.layer.costmap is None else self.layer.costmap.copy()

    def matches(self, expected: np.ndarray) -> bool:
        grid = self.grid()
        return grid is not None and np.array_equal(grid, expected)

    def close(self) -> None:
        for sub in self._subs:
            sub.unregister()


def test_the_static_layer_grid_equals_the_zone_layer_after_100_random_events(
    ros_node: RosMaster, school_broker: tuple[Path, BrokerThread]
) -> None:
    site_dir, broker = school_broker
    site = load_site(site_dir)
    grid = site.grid
    frame = GridFrame(grid.width, grid.height, grid.resolution, grid.origin[0], grid.origin[1])
    reference = ZoneFeed(site.spec, frame)
    nodes: dict[str, MqttBus] = {
        n.id: connect_with_credentials(broker.host, broker.port, broker.credentials(n.id))
        for n in site.spec.nodes
    }
    operator = connect_with_credentials(broker.host, broker.port, broker.credentials("operator"))
    # no hold: each update is exactly the window that changed (the hold is tested in test_ros_zone_grid.py)
    bridge = WsnavChild(
        ["ros", "bridge", *bridge_args(site_dir, broker, "--update-hold", "0")], ros_node.env()
    )
    peer: StaticLayerPeer | None = None
    try:
        bridge.wait_for("zone bridge for site school", 30)
        echo = subprocess.run(
            ["rostopic", "echo", "-n", "1", "/wsn/zone_grid/info"],
            env=ros_node.env(),
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert f"width: {grid.width}" in echo.stdout and f"height: {grid.height}" in echo.stdout, echo
        require_tool("rostopic")
        peer = StaticLayerPeer()
        wait_until(lambda: peer is not None and peer.grid() is not None, 20, "the whole grid on subscribe")
        rng = random.Random(20261123)
        seq = dict.fromkeys(nodes, 1000)
        t = 0.0
        seen: set[int] = set()

        def send(bus: MqttBus, topic: str, payload: bytes) -> None:
            nonlocal t
            t += 0.01
            bus.publish(topic, payload, qos=1, retain=True)
            reference.take([Message(topic, payload, True, t)], t)

        for i in range(EVENTS):
            kind = rng.choice(["state", "state", "state", "offline", "online", "block", "unblock"])
            node = rng.choice(site.spec.nodes)
            if kind == "state":
                seq[node.id] += 1
                msg = ZoneState(
                    zone=node.zone,
                    node=node.id,
                    state=rng.choice(["clear", "caution", "blocked"]),
                    seq=seq[node.id],
                )
                send(nodes[node.id], topics.zone_state(site.name, node.zone, node.id), msg.to_payload())
            elif kind in ("offline", "online"):
                status = NodeStatus(node=node.id, status=kind)
                send(nodes[node.id], topics.node_status(site.name, node.id), status.to_payload())
            elif kind == "block":
                block_id = f"b{rng.randrange(3)}"
                if rng.random() < 0.5:
                    block = OperatorBlock(zone=rng.choice(site.spec.zones).id)
                else:
                    x, y = rng.uniform(2, 45), rng.uniform(2, 28)
                    block = OperatorBlock(
                        polygon=[(x, y), (x + rng.uniform(0.5, 4), y), (x, y + rng.uniform(0.5, 4))]
                    )
                send(operator, topics.operator_block(site.name, block_id), block.to_payload())
            else:
                send(operator, topics.operator_block(site.name, f"b{rng.randrange(3)}"), b"")
            expected = reference.costs
            seen.update(int(c) for c in np.unique(expected))
            wait_until(
                lambda: peer.matches(expected),  # noqa: B023  (checked before the next event)
                10,
                f"event {i} ({kind}) to reach the StaticLayer",
            )
        assert peer.grids == 1, "a change must travel as an update, never as the whole grid again"
        assert peer.latching == "1", "latched, so rosbag play and relays latch it for late subscribers too"
        whole = grid.width * grid.height
        # one zone's window, or the box around the two zones a moved operator block touched at once
        assert peer.update_cells and float(np.median(peer.update_cells)) < whole / 100, peer.update_cells
        assert max(peer.update_cells) < whole / 2, peer.update_cells
        assert seen >= {0, 200, 254, 255}, seen  # clear, caution, blocked and unknown all travelled
    finally:
        if peer is not None:
            peer.close()
        bridge.stop()
        operator.close()
        for bus in nodes.values():
            bus.close()
