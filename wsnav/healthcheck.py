"""Health checks for the containers of docker-compose.yml: what an MQTT client of the site would see.

A live process is not a healthy service: the broker must accept a login, the zone simulator's nodes must be
`online`, the robot agent must be reporting. Each check connects with real credentials, prints one line, and
exits 0 (healthy) or 1 (not). The MQTT checks log in with the operator's file only, as its `health` tool: on
Mosquitto a client id is its login, so a check logged in as the robot took the running robot's connection over
(and one as a node, or as the dashboard, would take theirs):

    python -m wsnav.healthcheck broker --broker HOST:PORT --credentials OPERATOR_FILE
    python -m wsnav.healthcheck nodes --site DIR --broker HOST:PORT --credentials OPERATOR_FILE
    python -m wsnav.healthcheck robot --site DIR --robot ID --broker HOST:PORT --credentials OPERATOR_FILE
    python -m wsnav.healthcheck mosquitto-store --data DIR [--autosave 2]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from wsnav.broker.mosquitto.store import GOOD, STORE, check_store, keep_good
from wsnav.runtime.cli_support import Parser, host_port
from wsnav.runtime.mqtt_bus import BusError, MqttBus, connect_with_credentials
from wsnav.schemas import topics
from wsnav.schemas.credentials import CredentialsError, load_credentials, tool_login
from wsnav.schemas.messages import NodeStatus, PayloadError, RobotStatus, parse_payload
from wsnav.schemas.site import Site, SiteError, load_site


class Unhealthy(Exception):
    """The service is not (yet) usable; str() is the one line to show."""


def _bus(args: argparse.Namespace) -> MqttBus:
    """A connected bus with the credentials file; a refused or unreachable broker is Unhealthy."""
    try:
        creds = load_credentials(args.credentials)
    except CredentialsError as exc:
        raise Unhealthy(str(exc)) from None
    if creds.role != "operator":
        raise Unhealthy(
            f"{args.credentials}: {creds.username}'s credentials; a health check logs in with the operator's "
            f"(operator.json): logged in as {creds.username} it would take {creds.username}'s own connection "
            "over on Mosquitto"
        )
    host, port = args.broker
    try:
        login = tool_login(creds, "health")  # the operator's: beside its console and watch on Mosquitto
        return connect_with_credentials(
            host,
            port,
            login,
            client_id=f"health-{login.username}-{os.getpid()}",
            timeout_s=args.timeout,
            copies=True,  # the nodes' and the robot's checks may run at the same moment
        )
    except BusError as exc:
        raise Unhealthy(str(exc)) from None


def check_broker(args: argparse.Namespace) -> str:
    bus = _bus(args)
    bus.close()
    return f"broker {args.broker[0]}:{args.broker[1]} accepts {args.credentials.stem}"


def check_nodes(args: argparse.Namespace) -> str:
    """Every node of the site has its retained status `online`."""
    site = _site(args.site)
    expected = {n.id for n in site.spec.nodes}
    bus = _bus(args)
    online: set[str] = set()
    try:
        bus.subscribe(topics.all_node_statuses(site.spec.name))
        deadline = time.monotonic() + args.timeout
        while online != expected and time.monotonic() < deadline:
            bus.wait(0.2)
            for msg in bus.poll():
                try:
                    status = parse_payload(NodeStatus, msg.payload)
                except PayloadError:
                    continue
                (online.add if status.status == "online" else online.discard)(status.node)
    finally:
        bus.close()
    missing = sorted(expected - online)
    if missing:
        raise Unhealthy(f"nodes not online: {', '.join(missing)}")
    return f"{len(online)} nodes online"


def check_robot(args: argparse.Namespace) -> str:
    """The robot agent published a status within the timeout (it reports at 2 Hz)."""
    site = _site(args.site)
    bus = _bus(args)
    try:
        bus.subscribe(topics.robot_status(site.spec.name, args.robot))
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:
            bus.wait(0.2)
            for msg in bus.poll():
                if msg.retain:
                    continue  # a retained status may be left over from a robot that is gone
                try:
                    status = parse_payload(RobotStatus, msg.payload)
                except PayloadError:
                    continue
                return f"{args.robot} reports {status.state}"
    finally:
        bus.close()
    raise Unhealthy(f"no status from {args.robot} within {args.timeout:g} s")


def check_mosquitto_store(args: argparse.Namespace) -> str:
    """Mosquitto saves its store every `autosave_interval`; when it cannot (its user may not write the folder), it
    only logs an error each time, and on a full disk it renames an empty or cut-short store into place without a
    word: either way the operator's blocks are gone at the next restart. So the store must be recent and whole,
    and its disk must have room for the next save. A whole store is kept (hard-linked) as `mosquitto.db.good`,
    which `wsnav broker mosquitto-restore` puts back before the next start."""
    store = args.data / STORE
    found = check_store(store)
    if found.problem == "missing":
        raise Unhealthy(
            f"{store}: Mosquitto has not saved its store (is {args.data} writable by Mosquitto's user? "
            "`wsnav broker mosquitto-config --data DIR --user USER` hands it over)"
        )
    free = _free_bytes(args.data)
    if found.problem is not None:
        kept = check_store(args.data / GOOD)
        last = (
            f"the last whole store ({GOOD}, {time.time() - kept.saved_at:.0f} s old, {kept.retained} retained "
            "messages) is kept: make room, then restart Mosquitto (`wsnav broker mosquitto-restore` first)"
            if kept.problem is None
            else f"no whole store was kept ({GOOD}: {kept.problem})"
        )
        raise Unhealthy(
            f"{store} is {found.problem}: Mosquitto's last save failed ({free} bytes free); {last}"
        )
    try:
        keep_good(args.data)
        kept_note = ""
    except OSError as exc:
        kept_note = f" (no copy kept: {exc.strerror})"
    size = store.stat().st_size
    if free < 2 * size + 65536:
        raise Unhealthy(
            f"{args.data}: {free} bytes free, too little for Mosquitto's next save of its {size}-byte store "
            "(a full disk: Mosquitto would save it empty, without a word)"
        )
    age = time.time() - found.saved_at
    if age > 2 * args.autosave + 5:
        raise Unhealthy(
            f"{store}: last saved {age:.0f} s ago, every {args.autosave:g} s expected (is {args.data} writable "
            "by Mosquitto's user? a full disk?)"
        )
    return f"{store} saved {age:.0f} s ago, whole ({found.retained} retained messages){kept_note}"


def _free_bytes(path: Path) -> int:
    try:
        stats = os.statvfs(path)
    except OSError:
        return 0
    return stats.f_bavail * stats.f_frsize


def _site(path: Path) -> Site:
    try:
        return load_site(path)
    except SiteError as exc:
        raise Unhealthy(str(exc)) from None


def build_parser() -> Parser:
    parser = Parser(
        prog="python -m wsnav.healthcheck", description=__doc__.splitlines()[0] if __doc__ else ""
    )
    sub = parser.add_subparsers(dest="check", required=True, parser_class=Parser)
    checks = {
        "broker": (check_broker, "the broker accepts a login with the credentials"),
        "nodes": (check_nodes, "every node of the site is online (operator credentials)"),
        "robot": (check_robot, "the robot agent is publishing its status"),
    }
    for name, (func, text) in checks.items():
        p = sub.add_parser(name, help=text)
        p.add_argument("--broker", type=host_port, default=("127.0.0.1", 1883), help="HOST:PORT")
        p.add_argument(
            "--credentials", type=Path, required=True, help="the operator's credentials file (operator.json)"
        )
        p.add_argument("--timeout", type=float, default=5.0, help="seconds (default 5)")
        if name != "broker":
            p.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
        if name == "robot":
            p.add_argument("--robot", required=True, help="robot id")
        p.set_defaults(func=func)
    store = sub.add_parser(
        "mosquitto-store", help="Mosquitto saved its retained messages lately, whole, with room"
    )
    store.add_argument("--data", type=Path, required=True, help="Mosquitto's persistence_location")
    store.add_argument(
        "--autosave",
        type=float,
        default=2.0,
        help="seconds between its saves (default 2: `autosave_interval 1`)",
    )
    store.set_defaults(func=check_mosquitto_store)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        print(args.func(args))
    except Unhealthy as exc:
        print(f"unhealthy: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
