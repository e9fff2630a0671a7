"""`wsnav ros2 bridge --robot` against a NavigateToPose action server on Debian's Cyclone DDS 0.10.2 (what Humble's
and Jazzy's rmw_cyclonedds run on), its own native process (tests/dds_peers/nav2_action_server.c, built with idlc
and gcc), through a real amqtt broker: MQTT goals reach it and its SUCCEEDED reaches MQTT, a goal in a zone that
becomes blocked is cancelled on the wire, a zone blocked around the robot sends it the goal to the way out (then
on to its goal), and a zone on the plan (/plan) flipping 20 times in 2 s does not make 20 goals.

What the stand-in leaves out of Nav2's bt_navigator: no behaviour tree, planner, controller, costmap or tf (its
goals never move the robot: the test moves it by publishing /amcl_pose, publishes planner_server's /plan, and
ends goals with "succeed"); no
feedback topic, no get_result service, no result timeout (every goal it saw stays in its status list); no goal
checks (frames, the `behavior_tree` field); no clientid matching before replying (rmw_cyclonedds's server waits up
to 100 ms for a client's reply reader when the request writer names a clientid; the bridge's names none); no
ros_discovery_info. Not here: rclcpp, Nav2 itself.

On Fast DDS 2.9.1 (rmw_fastrtps, Humble's and Jazzy's default rmw), tests/dds_peers/nav2_fastdds_server.cpp: the
same server as rmw_fastrtps lays a service out (the request's CDR alone, its id taken from the DATA's sample
identity, the reply naming it in related_sample_identity): an MQTT goal reaches it and arrives, a goal in a zone
that becomes blocked is cancelled by its UUID. It leaves out what the Cyclone one does, and also: rmw_fastrtps's
wait for the client's reply reader before replying (it waits only when the request names that reader in
related_sample_identity, which the bridge's do not), its ASYNCHRONOUS publish mode and its XML profiles,
/plan; and the bridge reads no replies there (cyclonedds-python does not show inline QoS), so a goal
bt_navigator rejects goes unseen.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.ros2_fixtures import NativePeer, bridge_args, clean_env, domain_id
from tests.ros_fixtures import Operator, WsnavChild, send_goal, slow_heartbeat_school, wait_until, zone_state
from wsnav.broker.amqtt.embedded import BrokerThread
from wsnav.runtime.mqtt_bus import MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.site import load_site

pytestmark = pytest.mark.slow

B = (29.0, 22.8)
Z1 = [(17.0, 5.9), (19.0, 5.9), (19.0, 8.5), (17.0, 8.5)]
"""School's z1 (south corridor by the science rooms), watched by n1."""


def in_box(x: float, y: float, polygon: list[tuple[float, float]]) -> bool:
    """Inside an axis-aligned zone (z1 and z4 are rectangles)."""
    xs, ys = [p[0] for p in polygon], [p[1] for p in polygon]
    return min(xs) <= x <= max(xs) and min(ys) <= y <= max(ys)


class Rig:
    def __init__(
        self, server: NativePeer, bridge: WsnavChild, operator: Operator, n1: MqttBus, z4: Any
    ) -> None:
        self.server, self.bridge, self.operator, self.n1, self.z4 = server, bridge, operator, n1, z4
        self.seq = 10

    def goals(self) -> list[dict[str, Any]]:
        return [s for s in list(self.server.samples) if "goal" in s]

    def cancels(self) -> list[dict[str, Any]]:
        return [s for s in list(self.server.samples) if "cancel" in s]

    def new_goal(self, after: int, what: str, timeout_s: float = 15.0) -> dict[str, Any]:
        wait_until(lambda: len(self.goals()) > after, timeout_s, what)
        return self.goals()[after]

    def set_z1(self, state: str) -> None:
        self.seq += 1
        zone_state(self.n1, "z1", "n1", state, self.seq)

    def state(self, want: str, what: str) -> Any:
        return self.operator.wait_status(what, lambda s: s.state == want)


@contextlib.contextmanager
def running_rig(tmp_path: Path, server_binary: Path, domain: int) -> Iterator[Rig]:
    """A stand-in server, the bridge (`--robot robot1`) and amqtt, the robot at A."""
    site_dir = slow_heartbeat_school(tmp_path)
    site = load_site(site_dir)
    with BrokerThread(site_dir) as broker:
        server = NativePeer("Nav2 stand-in", [str(server_binary), str(domain)], clean_env(), commands=True)
        bus = connect_with_credentials(broker.host, broker.port, broker.credentials("operator"))
        bus.subscribe(topics.robot_status("school", "robot1"))
        z4 = next(z for z in site.spec.zones if z.id == "z4")
        node4 = next(n.id for n in site.spec.nodes if n.zone == "z4")
        links = {
            n: connect_with_credentials(broker.host, broker.port, broker.credentials(n))
            for n in ("n1", node4)
        }
        args = bridge_args(
            site, f"{broker.host}:{broker.port}", broker.credentials_dir / "robot1.json", domain
        )
        bridge = WsnavChild([*args, "--robot", "robot1", "--nav2-resend"], clean_env())
        try:
            bridge.wait_for("MQTT broker connected", 60)
            server.command("pose 12.0 7.2 0.0")  # at A
            rig = Rig(server, bridge, Operator(bus, "school"), links["n1"], (z4, links[node4], node4))
            rig.operator.wait_status("the robot's status from its /amcl_pose", lambda s: s.pose[0] == 12.0)
            yield rig
        finally:
            code = server.stop()
            bridge.stop()
            print("bridge output:", *bridge.lines, sep="\n")  # shown when a test fails
            bus.close()
            for link in links.values():
                link.close()
    assert code == 0, f"the stand-in exited {code}: {server.stderr()}"


@pytest.fixture
def rig(tmp_path: Path, nav2_server: Path) -> Iterator[Rig]:
    with running_rig(tmp_path, nav2_server, domain_id() + 5) as rig:
        yield rig


@pytest.fixture
def fast_rig(tmp_path: Path, nav2_fastdds_server: Path) -> Iterator[Rig]:
    with running_rig(tmp_path, nav2_fastdds_server, domain_id() + 7) as rig:
        yield rig


def test_nav2_gets_mqtt_goals_cancels_in_blocked_zones_escapes_and_is_not_flooded(rig: Rig) -> None:
    # A pose that is no place is dropped (its status could not be published), the last good one kept.
    rig.server.command("pose nan nan 0.0")
    rig.bridge.wait_for("dropped a pose", 15)

    # An MQTT goal goes to Nav2 as a NavigateToPose goal; its SUCCEEDED comes back as "arrived".
    send_goal(rig.operator, "B")
    goal = rig.new_goal(0, "the MQTT goal at the action server")
    assert (goal["x"], goal["y"], goal["frame_id"]) == (*B, "map")
    status = rig.state("navigating", "navigating to B")
    assert status.goal == "B"
    rig.server.command("succeed")
    rig.state("arrived", "arrived, from the server's SUCCEEDED")

    # A goal in a zone that becomes blocked is cancelled at the server.
    z4, node4_link, node4 = rig.z4
    inside = (25.0, 15.0)
    assert in_box(*inside, [tuple(p) for p in z4.polygon])
    send_goal(rig.operator, [*inside, 0.0])
    goal = rig.new_goal(1, "the goal into z4")
    rig.state("navigating", "navigating into z4")
    zone_state(node4_link, "z4", node4, "blocked", 5)
    wait_until(lambda: bool(rig.cancels()), 15, "the cancel of the goal in blocked z4")
    assert rig.cancels()[0]["cancel"] == goal["goal"]
    status = rig.state("cancelled", "cancelled")
    assert status.reason is not None and "z4" in status.reason

    # A zone blocked around the robot: the one goal out of it, then on to B once at the exit.
    rig.server.command("pose 18.0 7.2 0.0")  # inside z1
    rig.operator.wait_status("the robot in z1", lambda s: s.pose[0] == 18.0)
    send_goal(rig.operator, "B")
    rig.new_goal(2, "the goal to B")
    rig.state("navigating", "navigating to B")
    rig.set_z1("blocked")
    out = rig.new_goal(3, "the goal out of z1")
    assert not in_box(out["x"], out["y"], Z1), out
    assert (out["x"], out["y"]) != B
    rig.operator.wait_status("the status saying so", lambda s: "leaving blocked z1" in (s.reason or ""))
    rig.server.command(
        f"pose {out['x']} {out['y']} 0.0"
    )  # out: the bridge goes on without waiting for the exit
    on = rig.new_goal(4, "the goal to B again, from the exit")
    assert (on["x"], on["y"]) == B
    assert len(rig.goals()) == 5 and not rig.cancels()[1:]

    # z1, on the plan, flips 20 times in 2 s: each flip is a replan for Algorithm 3, the re-sends rate-limited
    # (without the policy's interval: 20).
    rig.server.command(f"plan {out['x']} {out['y']} 28.0 7.2")  # east along the south corridor, through z1
    time.sleep(0.5)
    before = len(rig.goals())
    start = time.monotonic()
    for i in range(20):
        rig.set_z1("clear" if i % 2 == 0 else "blocked")
        time.sleep(0.1)
    span = time.monotonic() - start  # 2 s, longer on a loaded machine
    time.sleep(1.5)
    resent = rig.goals()[before:]
    assert 1 <= len(resent) <= span / 0.5 + 2, (span, resent)
    assert all((g["x"], g["y"]) == B for g in resent), resent
    rig.state("navigating", "still navigating to B")
    assert rig.bridge.proc.poll() is None, "the bridge still runs"


def test_nav2_on_fast_dds_gets_mqtt_goals_in_its_layout_and_cancels_by_uuid(fast_rig: Rig) -> None:
    """rmw_fastrtps's layout: the request is the goal's CDR alone (a Cyclone header in front would be read as the
    UUID and shift the pose), its id the DATA's sample identity, here the bridge's Cyclone writer (vendor 1.16)."""
    rig = fast_rig
    send_goal(rig.operator, "B")
    goal = rig.new_goal(0, "the MQTT goal at the Fast DDS action server")
    assert (goal["x"], goal["y"], goal["frame_id"]) == (*B, "map"), goal
    assert goal["writer"].startswith("0110") and goal["seq"] >= 1, goal
    status = rig.state("navigating", "navigating to B, from the server's status")
    assert status.goal == "B"
    rig.server.command("succeed")
    rig.state("arrived", "arrived, from the server's SUCCEEDED")

    _, node4_link, node4 = rig.z4
    inside = (25.0, 15.0)
    send_goal(rig.operator, [*inside, 0.0])
    goal = rig.new_goal(1, "the goal into z4")
    assert (goal["x"], goal["y"]) == inside, goal
    rig.state("navigating", "navigating into z4")
    zone_state(node4_link, "z4", node4, "blocked", 5)
    wait_until(lambda: bool(rig.cancels()), 15, "the cancel of the goal in blocked z4")
    assert rig.cancels()[0]["cancel"] == goal["goal"]
    status = rig.state("cancelled", "cancelled, from the server's CANCELED")
    assert status.reason is not None and "z4" in status.reason
    assert not any("unreadable" in s for s in rig.server.samples), rig.server.samples
    assert rig.bridge.proc.poll() is None, "the bridge still runs"


def test_servers_on_both_rmws_at_once_get_no_goal_and_the_bridge_says_why_in_one_line(
    tmp_path: Path, nav2_server: Path, nav2_fastdds_server: Path
) -> None:
    """A site runs one rmw: with a rmw_cyclonedds and a rmw_fastrtps navigate_to_pose server matched at once,
    either layout would be garbage to one of them, so the bridge holds the MQTT goal and says why, once."""
    site_dir = slow_heartbeat_school(tmp_path)
    site = load_site(site_dir)
    domain = domain_id() + 6
    with BrokerThread(site_dir) as broker:
        servers = [
            NativePeer(name, [str(binary), str(domain)], clean_env(), commands=True)
            for name, binary in (
                ("Cyclone stand-in", nav2_server),
                ("Fast DDS stand-in", nav2_fastdds_server),
            )
        ]
        bus = connect_with_credentials(broker.host, broker.port, broker.credentials("operator"))
        bus.subscribe(topics.robot_status("school", "robot1"))
        args = bridge_args(
            site, f"{broker.host}:{broker.port}", broker.credentials_dir / "robot1.json", domain
        )
        bridge = WsnavChild([*args, "--robot", "robot1"], clean_env())
        try:
            bridge.wait_for("MQTT broker connected", 60)
            operator = Operator(bus, "school")
            for x, server in zip((12.0, 13.0), servers, strict=True):  # both matched before the goal
                server.command(f"pose {x} 7.2 0.0")
                operator.wait_status(f"the pose from the {server.name}", lambda s, x=x: s.pose[0] == x)
            send_goal(operator, "B")
            bridge.wait_for("rmw_cyclonedds AND rmw_fastrtps", 20)
            time.sleep(1.0)
            assert sum("rmw_cyclonedds AND rmw_fastrtps" in s for s in bridge.lines) == 1, bridge.lines
            assert not [s for server in servers for s in server.samples], "no goal reached either server"
        finally:
            codes = [server.stop() for server in servers]
            bridge.stop()
            print("bridge output:", *bridge.lines, sep="\n")
            bus.close()
    assert codes == [0, 0]
