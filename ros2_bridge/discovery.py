"""How the bridge meets ROS 2's graph: its Cyclone DDS configuration, built from ROS 2's environment as
rmw_cyclonedds builds its own, and the node it announces.

rmw_cyclonedds (Jazzy's `check_create_domain`) puts a fragment of its own before the user's `CYCLONEDDS_URI`, so
the user's file still wins; the bridge does the same, so a robot started with `ROS_LOCALHOST_ONLY=1` or
`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST` finds the bridge with no hand-written `CYCLONEDDS_URI`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from wsnav.runtime.cli_support import CliError

NODE_NAMESPACE = "/"
NODE_NAME = "wsnav_ros2_bridge"
"""The node the bridge announces on ros_discovery_info: what `ros2 node list` shows, and `ros2 topic info -v` as
its topics' publisher."""
RANGES = ("SUBNET", "LOCALHOST", "OFF", "SYSTEM_DEFAULT")
"""ROS_AUTOMATIC_DISCOVERY_RANGE's values (rcl's `rcl_get_automatic_discovery_range`); unset is SUBNET."""
MAX_AUTO_PARTICIPANT_INDEX = 32
"""rmw_cyclonedds's: how many participants on one host a localhost range reaches by unicast."""
CYCLONE_VENDOR_ID = "1.16"
IGNORE_TYPE_INFORMATION = (
    f"<Compatibility><IgnoreTypeInformation>{CYCLONE_VENDOR_ID}</IgnoreTypeInformation></Compatibility>"
)
"""Match Cyclone readers by type name, as rmw_cyclonedds's readers (which carry no XTypes type information) are
matched: a Cyclone 11 reader's int8 (TK_INT8) is not assignable to the TK_CHAR8 the bridge announces."""

_AUTO_INDEX = (
    f"<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>{MAX_AUTO_PARTICIPANT_INDEX}"
    "</MaxAutoParticipantIndex>"
)


@dataclass(frozen=True)
class Discovery:
    """How far the bridge looks for ROS 2 peers: rmw's discovery options."""

    range: str
    """One of RANGES."""
    static_peers: tuple[str, ...] = ()
    localhost_only: bool = False
    """ROS_LOCALHOST_ONLY=1 (Humble's switch; Jazzy still honours it as the LOCALHOST range)."""

    def describe(self) -> str:
        """One phrase for the start line."""
        if self.localhost_only:
            return "discovery on this host only (ROS_LOCALHOST_ONLY=1)"
        peers = f", static peers {', '.join(self.static_peers)}" if self.static_peers else ""
        return f"discovery range {self.range}{peers}"


def discovery_from_env(env: Mapping[str, str] | None = None) -> Discovery:
    """rcl's reading of ROS_LOCALHOST_ONLY, ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_STATIC_PEERS; a value rcl
    would only warn about is refused here in one line (a bridge started with a typo should not look elsewhere)."""
    env = os.environ if env is None else env
    localhost = env.get("ROS_LOCALHOST_ONLY", "").strip()
    if localhost not in ("", "0", "1"):
        raise CliError(f"ROS_LOCALHOST_ONLY={localhost!r}: 1 (this host only) or 0")
    if localhost == "1":  # rcl: localhost_only overrides the range and drops the static peers
        return Discovery("LOCALHOST", (), localhost_only=True)
    value = env.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "").strip()
    if value and value not in RANGES:
        raise CliError(f"ROS_AUTOMATIC_DISCOVERY_RANGE={value!r}: one of {', '.join(RANGES)}")
    range_ = value or "SUBNET"
    peers = tuple(p.strip() for p in env.get("ROS_STATIC_PEERS", "").split(";") if p.strip())
    for peer in peers:
        if any(c in peer for c in "<>\"'&") or any(c.isspace() for c in peer):
            raise CliError(f"ROS_STATIC_PEERS: {peer!r} is not a host name or address")
    if range_ == "OFF":
        peers = ()  # rcl does not read static peers when discovery is off
    return Discovery(range_, peers)


def cyclone_config(discovery: Discovery, user_uri: str, pid: int) -> str:
    """The configuration string for the bridge's Cyclone domain: rmw_cyclonedds's fragment for `discovery`,
    IgnoreTypeInformation, then the user's CYCLONEDDS_URI (last, so it overrides ours)."""
    general = ""
    disc = ""
    peers: list[str] = []
    if discovery.localhost_only:
        # Humble's rmw_cyclonedds: the loopback interface only; Jazzy's (ROS_LOCALHOST_ONLY=1 is its
        # LOCALHOST range): unicast to this host's participant ports. Both, so robots of either distro meet it.
        general = '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
        disc = _AUTO_INDEX
        peers = ["localhost"]
    elif discovery.range == "LOCALHOST":
        general = "<AllowMulticast>false</AllowMulticast>"
        disc = _AUTO_INDEX
        peers = ["localhost", *discovery.static_peers]
    elif discovery.range == "OFF":
        general = "<AllowMulticast>false</AllowMulticast>"
        disc = f"<ParticipantIndex>none</ParticipantIndex><Tag>ros_discovery_off_{pid}</Tag>"
    elif discovery.range == "SUBNET":  # rmw sets the participant index for this range too, peers or not
        disc = _AUTO_INDEX
        peers = list(discovery.static_peers)
    if peers:
        disc += "<Peers>" + "".join(f"<Peer address={quoteattr(p)}/>" for p in peers) + "</Peers>"
    ours = "<CycloneDDS><Domain>"
    if general:
        ours += f"<General>{general}</General>"
    if disc:
        ours += f"<Discovery>{disc}</Discovery>"
    ours += f"{IGNORE_TYPE_INFORMATION}</Domain></CycloneDDS>"
    return ours + ("," + user_uri if user_uri.strip() else "")
