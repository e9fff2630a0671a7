"""What every zone bridge (ROS 1's `wsnav ros bridge`, ROS 2's `wsnav ros2 bridge`) does on the MQTT side, without
rospy: read the site and the robot's credentials, refuse a caution cost no OccupancyGrid value carries, log in to
the broker while it may still be down, and say once per change whether the link is up.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from wsnav.ros_bridge.zone_grid import UnrepresentableCost, ZoneGridCodec
from wsnav.runtime.cli_support import CliError, read_robot_credentials
from wsnav.runtime.clock import WallClock
from wsnav.runtime.mqtt_bus import BusError, MqttBus, connect_with_credentials
from wsnav.schemas.credentials import Credentials
from wsnav.schemas.site import Site, SiteError, load_site


@dataclass(frozen=True)
class BridgeSite:
    site: Site
    creds: Credentials
    codec: ZoneGridCodec


def load_bridge_site(site_path: Path, credentials: Path) -> BridgeSite:
    """The site, the robot's credentials checked against it, and the codec checked against its caution cost;
    each problem a one-line CliError."""
    try:
        site = load_site(site_path)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    creds = read_robot_credentials(credentials, site)
    codec = ZoneGridCodec()
    try:
        codec.check({site.spec.policy.caution_cost})
    except UnrepresentableCost as exc:
        raise CliError(f"{site.path}: policy.caution_cost: {exc}") from None
    return BridgeSite(site, creds, codec)


def start_broker_link(broker: tuple[str, int], creds: Credentials, tls_ca: Path | None) -> MqttBus:
    """A bus that keeps connecting in the background: a bridge serves its grid while the broker is down."""
    host, port = broker
    try:
        return connect_with_credentials(host, port, creds, clock=WallClock(), wait=False, tls_ca=tls_ca)
    except BusError as exc:
        raise CliError(str(exc)) from None


class LinkWatch:
    """Says, loudly and once per change, when the MQTT link is down (the grid still serves its last states, read
    by the site's stale policy) and when it is back: a bridge without its broker must keep the grid up, or a
    StaticLayer waiting for its map holds move_base's start. While down, it says so again every REPEAT_S."""

    REPEAT_S = 60.0

    def __init__(self, stale_policy: str, now: float) -> None:
        self.stale_policy = stale_policy
        self.up: bool | None = None
        self._said_at = now

    def check(self, connected: bool, now: float) -> str | None:
        if connected == self.up and (connected or now - self._said_at < self.REPEAT_S):
            return None
        was, self.up, self._said_at = self.up, connected, now
        if connected:
            return (
                "MQTT broker connected: zone states are live"
                if was is None
                else "MQTT broker back: zone states are live again"
            )
        return (
            "MQTT broker unreachable: the zone grid is served but not updated; zones whose nodes fall silent "
            f"are read by the site's stale policy ({self.stale_policy!r})"
        )
