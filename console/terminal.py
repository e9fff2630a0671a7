"""`wsnav status | watch | block | unblock | goal | cancel | node-command`: the console's view and steering in a
terminal."""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sqlite3
import sys
import time
from collections.abc import Callable
from typing import Any

from wsnav.console import operator_commands as commands
from wsnav.console.event_log import log_path, open_for_reading
from wsnav.console.live_state import subscriptions
from wsnav.console.operator_commands import CommandError, Publication
from wsnav.console.operator_link import OperatorLink, connect
from wsnav.console.site_view import SiteView
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.messages import MAX_OPERATOR_PAYLOAD_BYTES, OperatorBlock, PayloadError, parse_payload
from wsnav.schemas.site import SiteError, load_site

SETTLE_QUIET_S = 0.5
"""`wsnav status` answers once no retained message came for this long (the broker's replay is over)."""
UNBLOCK_LOOKUP_S = 2.0
"""How long `wsnav unblock` waits for the broker's retained copy of the block before calling the id unknown."""


def _gather(
    link: OperatorLink, view: SiteView, quiet_s: float, max_s: float, *, replay: bool = False
) -> None:
    """Take in what arrives for `max_s`, or with `replay` until the broker's retained replay is over: no retained
    message for `quiet_s` (a 2 Hz robot's live statuses never make the bus quiet, so they do not count)."""
    start = time.monotonic()
    deadline = start + max_s
    last_replayed = start + quiet_s  # the first retained message may take a round trip more
    while (now := time.monotonic()) < deadline:
        if replay and now - last_replayed >= quiet_s:
            break
        wait = deadline - now if not replay else min(deadline, last_replayed + quiet_s) - now
        link.bus.wait(max(0.0, wait))
        for msg in link.bus.poll():
            view.apply(msg.topic, msg.payload, msg.received_at, msg.retain)
            if msg.retain:
                last_replayed = time.monotonic()
    for msg in link.bus.poll():
        view.apply(msg.topic, msg.payload, msg.received_at, msg.retain)


def _subscribed(args: argparse.Namespace, purpose: str) -> tuple[OperatorLink, SiteView]:
    link = connect(args, purpose)
    view = SiteView(link.site)
    for flt in subscriptions(link.site.name):
        link.bus.subscribe(flt)
    return link, view


def _table(headers: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(headers)]
    line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip()  # noqa: E731
    return [line(headers), *(line(r) for r in rows)]


def _age(seconds: float | None) -> str:
    if seconds is None:
        return "never"
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def render(snapshot: dict[str, Any]) -> str:
    """The terminal's one table per kind, from the same snapshot `GET /api/state` gives."""
    out: list[str] = [
        f"site {snapshot['site']}   {time.strftime('%H:%M:%S', time.localtime(snapshot['now']))}"
    ]
    if snapshot.get("broker_connected") is False:
        out.append("!! the MQTT broker is not reachable: what follows may be out of date")
    nodes = snapshot["nodes"]

    def link(n: dict[str, Any]) -> str:
        """A node known only from the broker's replay has said nothing live yet: not "silent", not "online"."""
        if n["online"] is False:
            return "offline"
        return "online" if n["fresh"] else ("silent" if n["age_s"] is not None else "no live word yet")

    out += [
        "",
        f"NODES ({sum(1 for n in nodes if n['online'] is not False and n['fresh'])}/{len(nodes)} reporting)",
    ]
    out += _table(
        ["node", "zone", "says", "link", "last heard", "diagnostics"],
        [
            [
                n["id"],
                n["zone"],
                n["state"] or "-",
                link(n),
                _age(n["age_s"]),
                " ".join(f"{k}={v}" for k, v in (n["info"] or {}).items()),
            ]
            for n in nodes
        ],
    )
    out += ["", "ZONES"]
    out += _table(
        ["zone", "state", "nodes", "operator blocks"],
        [
            [
                z["id"],
                z["state"] + (f" (stale: {' '.join(z['stale_nodes'])})" if z["stale_nodes"] else ""),
                " ".join(z["nodes"]),
                " ".join(z["operator_blocks"]),
            ]
            for z in snapshot["zones"]
        ],
    )
    out += ["", "ROBOTS"]
    rows = []
    for r in snapshot["robots"]:
        if r.get("state") is None:
            rows.append([r["id"], "no status", "", "", "", "", "", ""])
            continue
        x, y, yaw = r["pose"]
        goal = (
            r["goal"]
            if isinstance(r["goal"], str) or r["goal"] is None
            else f"{r['goal'][0]:.1f},{r['goal'][1]:.1f}"
        )
        rows.append(
            [
                r["id"],
                r["state"],
                f"{x:.2f},{y:.2f} {math.degrees(yaw):.0f}°",
                goal or "-",
                str(r["replans"]),
                " ".join(r["blocked_zones"]),
                _age(r["age_s"]),
                r.get("reason") or "",
            ]
        )
    out += _table(["robot", "state", "pose", "goal", "replans", "blocked zones", "age", "reason"], rows)
    out += ["", "OPERATOR BLOCKS"]
    out += _table(
        ["block", "where", "left", "reason"],
        [
            [
                b["id"],
                b["zone"] or f"polygon of {len(b['polygon'])}",
                "until lifted" if b["left_s"] is None else _age(b["left_s"]),
                b["reason"] or "",
            ]
            for b in snapshot["blocks"]
        ],
    )
    return "\n".join(out)


def fit(text: str, rows: int, columns: int) -> str:
    """The screen's worth of `text`: lines cut at the width, and when too long, the top (the site, the time and
    any outage line stay in view) and one line saying how much was left out, instead of scrolling them away."""
    lines = [line[:columns] for line in text.splitlines()]
    if len(lines) < rows:
        return "\n".join(lines)
    keep = max(1, rows - 2)
    more = f"... {len(lines) - keep} more lines (a taller window, or wsnav status)"
    return "\n".join([*lines[:keep], more[:columns]])


def status_command(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.wait) and args.wait > 0):
        raise CliError(f"--wait {args.wait:g}: expected a positive number of seconds")
    link, view = _subscribed(args, "status")
    try:
        _gather(link, view, SETTLE_QUIET_S, args.wait, replay=True)
        view.expire(link.clock.now())
        snapshot = view.snapshot(link.clock.now())
    finally:
        link.bus.close()
    snapshot["broker_connected"] = True
    print(json.dumps(snapshot, indent=1) if args.json else render(snapshot))
    return 0


def watch_command(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.every) and args.every >= 0.1):
        raise CliError(f"--every {args.every:g}: expected at least 0.1 s")
    link, view = _subscribed(args, "watch")
    try:
        while True:
            _gather(link, view, args.every, args.every)
            view.expire(link.clock.now())
            snapshot = view.snapshot(link.clock.now())
            snapshot["broker_connected"] = link.bus.connected
            size = shutil.get_terminal_size()
            sys.stdout.write("\x1b[H\x1b[2J" + fit(render(snapshot), size.lines, size.columns) + "\n")
            sys.stdout.flush()
    finally:
        link.bus.close()


def _publish(args: argparse.Namespace, verb: str, make: Callable[[OperatorLink], Publication]) -> None:
    """Connect as the operator, make the message for the site, send it and wait for the broker's ack."""
    link = connect(args, verb)
    try:
        pub = make(link)
    except CommandError as exc:
        link.bus.close()
        raise CliError(str(exc)) from None
    _send(link, pub)


def _send(link: OperatorLink, pub: Publication) -> None:
    try:
        ok = link.bus.publish_confirmed(pub.topic, pub.payload, retain=pub.retain)
    finally:
        link.bus.close()
    if not ok:
        raise CliError("the broker did not confirm the message in time: it may not have been delivered")


def _parse_xy(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CliError(f"{what}: expected numbers x,y, got {text!r}") from None
    if not all(math.isfinite(v) for v in values):
        raise CliError(f"{what}: expected finite numbers, got {text!r}")
    return values


def block_command(args: argparse.Namespace) -> int:
    if args.extend is not None:
        return _extend_block(args)
    if (args.zone is None) == (args.polygon is None):
        raise CliError("give a ZONE or --polygon X,Y X,Y X,Y (not both)")
    polygon = None
    if args.polygon is not None:
        corners = [_parse_xy(p, "--polygon") for p in args.polygon]
        if any(len(c) != 2 for c in corners):
            raise CliError("--polygon: each corner is X,Y")
        polygon = [(c[0], c[1]) for c in corners]
    try:
        duration = commands.parse_duration(args.duration) if args.duration is not None else None
    except CommandError as exc:
        raise CliError(f"--for: {exc}") from None
    made: list[str] = []

    def make(link: OperatorLink) -> Publication:
        block_id, pub = commands.block(
            link.site,
            now=link.clock.now(),
            duration_s=duration,
            zone=args.zone,
            polygon=polygon,
            reason=args.reason,
            block_id=args.block_id,
        )
        made.append(block_id)
        return pub

    _publish(args, "block", make)
    block_id = made[0]
    print(f"blocked: {block_id}" + (f" for {args.duration}" if args.duration else " until unblocked"))
    return 0


def unblock_command(args: argparse.Namespace) -> int:
    """Lift a block the broker holds; an id it does not hold (a typo, a block already lifted or expired) is one
    line and exit 2, as the console's API answers 404, rather than "lifted"."""
    link = connect(args, "unblock")
    try:
        pub = commands.unblock(link.site, args.block_id)
    except CommandError as exc:
        link.bus.close()
        raise CliError(str(exc)) from None
    _held_block(link, pub.topic, args.block_id)
    _send(link, pub)
    print(f"lifted: {args.block_id}")
    return 0


def _held_block(link: OperatorLink, topic: str, block_id: str) -> bytes:
    """The block the broker holds on `topic` (any retained word, even one the view would drop: a block on a
    removed zone); none within UNBLOCK_LOOKUP_S is one line and exit 2."""
    link.bus.subscribe(topic)
    held = b""
    deadline = time.monotonic() + UNBLOCK_LOOKUP_S
    while not held and (left := deadline - time.monotonic()) > 0:
        if link.bus.wait(left):
            held = next((m.payload for m in link.bus.poll() if m.topic == topic and m.payload), b"")
    if not held:
        link.bus.close()
        raise CliError(f"no active block {block_id!r} (`wsnav status` lists the blocks in force)")
    return held


def _extend_block(args: argparse.Namespace) -> int:
    """`wsnav block --extend ID --for TIME`: the block the broker holds, its expiry TIME later, same id."""
    if (
        args.zone is not None
        or args.polygon is not None
        or args.reason is not None
        or args.block_id is not None
    ):
        raise CliError("--extend ID takes only --for TIME (the block keeps its area and reason)")
    if args.duration is None:
        raise CliError("--extend ID needs --for TIME: how much longer (e.g. --for 10m)")
    try:
        by_s = commands.parse_duration(args.duration)
    except CommandError as exc:
        raise CliError(f"--for: {exc}") from None
    link = connect(args, "block")
    try:
        topic = commands.unblock(link.site, args.extend).topic
        current = parse_payload(
            OperatorBlock, _held_block(link, topic, args.extend), max_bytes=MAX_OPERATOR_PAYLOAD_BYTES
        )
        pub = commands.extend(link.site, args.extend, current, now=link.clock.now(), by_s=by_s)
    except (CommandError, PayloadError) as exc:
        link.bus.close()
        raise CliError(f"{args.extend}: {exc}") from None
    _send(link, pub)
    expires = json.loads(pub.payload)["expires_at"]
    print(f"extended: {args.extend} until {time.strftime('%H:%M:%S', time.localtime(expires))}")
    return 0


def goal_command(args: argparse.Namespace) -> int:
    target: str | tuple[float, float, float] = args.point
    if args.point[:1].isdigit() or args.point[:1] in "-.":
        values = _parse_xy(args.point, "POINT")
        if len(values) not in (2, 3):
            raise CliError(f"POINT: expected a named point, x,y or x,y,yaw; got {args.point!r}")
        target = (values[0], values[1], values[2] if len(values) == 3 else 0.0)
    _publish(args, "goal", lambda link: commands.goal(link.site, args.robot, target))
    print(f"goal sent to {args.robot}: {args.point}")
    return 0


def clear_status_command(args: argparse.Namespace) -> int:
    _publish(args, "clear-status", lambda link: commands.clear_status(link.site, args.robot))
    print(f"{args.robot}'s retained status cleared (its agent, if running, publishes a new one)")
    return 0


def cancel_command(args: argparse.Namespace) -> int:
    _publish(args, "cancel", lambda link: commands.cancel(link.site, args.robot))
    print(f"cancel sent to {args.robot}")
    return 0


NODE_ACTIONS: dict[str, commands.NodeCommandName] = {
    "restart": "restart",
    "send-info": "send_info",
    "heartbeat": "set_heartbeat",
}


def node_command_command(args: argparse.Namespace) -> int:
    """`wsnav node-command NODE restart|send-info|heartbeat SECONDS`: one QoS 1 message the broker confirms."""
    action = NODE_ACTIONS[args.action]
    if (args.seconds is None) == (action == "set_heartbeat"):
        raise CliError("heartbeat takes SECONDS (e.g. heartbeat 10); restart and send-info take nothing")
    heartbeat_s = None
    if args.seconds is not None:
        try:
            heartbeat_s = float(args.seconds)
        except ValueError:
            raise CliError(f"SECONDS: expected a number, got {args.seconds!r}") from None
        if not math.isfinite(heartbeat_s):
            raise CliError(f"SECONDS: expected a finite number, got {args.seconds!r}")
    _publish(
        args, "node-command", lambda link: commands.node_command(link.site, args.node, action, heartbeat_s)
    )
    print(f"{args.action} sent to {args.node}" + (f" ({heartbeat_s:g} s)" if heartbeat_s is not None else ""))
    return 0


def log_command(args: argparse.Namespace) -> int:
    """`wsnav log`: the newest events the console kept, oldest first (no broker needed)."""
    if args.last < 1:
        raise CliError(f"--last {args.last}: expected at least 1")
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    path = log_path(args.state_dir, site.name)
    try:
        events = open_for_reading(path)
    except sqlite3.Error as exc:
        raise CliError(f"{path}: not an event log ({exc})") from None
    if events is None:
        raise CliError(f"no event log at {path} (`wsnav console` writes it; give its --state-dir)")
    try:
        for e in events.recent(args.last):
            if args.json:
                print(json.dumps({"t": e.t, "kind": e.kind, "subject": e.subject, "text": e.text}))
            else:
                print(f"{time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(e.t))}  {e.text}")
    finally:
        events.close()
    return 0
