"""`wsnav firmware ota` and `config`: the app, or the configuration (Wi-Fi, broker address), of running nodes
changed over MQTT, as the site's operator; and `wsnav firmware logs`: their last log lines, asked for.

Here, not in firmware/cli.py: it logs in as the operator (`wsnav node-command`'s connection and command,
console/operator_link.py and console/operator_commands.py), and the firmware component does not import the console
(tests/test_component_imports.py). The transfers themselves are firmware/ota.py and firmware/ota_config.py.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.firmware.build import DEVICE, BuildError
from wsnav.runtime.cli_support import CliError, host_port
from wsnav.schemas.credentials import (
    UPDATE_KEY_FILE,
    fallback_ap_key,
    fallback_ap_ssid,
    node_update_key,
)

if TYPE_CHECKING:
    from wsnav.console.operator_link import OperatorLink
    from wsnav.firmware.ota import NodeTransfer
    from wsnav.runtime.cli_support import Parser
    from wsnav.schemas.messages import NodeCommandName
    from wsnav.schemas.site_file import SiteFile


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    """`ota` under `wsnav firmware` (which firmware/cli.py registers first)."""
    from wsnav.console.cli import operator_arguments

    firmware = sub.choices["firmware"]
    fw_sub = next(a for a in firmware._actions if isinstance(a, argparse._SubParsersAction))
    o = fw_sub.add_parser(
        "ota",
        help="update running nodes' app over MQTT: build, command, serve the chunks, wait until each confirms",
    )
    operator_arguments(o)
    o.add_argument("--nodes", required=True, metavar="N1,N2", help="the nodes to update, comma-separated")
    o.add_argument(
        "--source", type=Path, default=DEVICE, help="the firmware sources to build (default firmware/device)"
    )
    _key_and_timeout(o, "signs the update")
    o.set_defaults(func=ota_command)

    c = fw_sub.add_parser(
        "config",
        help="send running nodes a new Wi-Fi network and/or broker address over MQTT; each tries it and goes back "
        "to its old one if it cannot get online with it",
    )
    operator_arguments(c)
    c.add_argument("--nodes", required=True, metavar="N1,N2", help="the nodes to change, comma-separated")
    c.add_argument(
        "--wifi",
        action="store_true",
        help="a new Wi-Fi network: its SSID on the first line of stdin, its key on the second (empty: open)",
    )
    c.add_argument(
        "--node-broker",
        type=host_port,
        metavar="HOST:PORT",
        help="the broker the nodes use from now on (its address as the nodes reach it)",
    )
    c.add_argument(
        "--new-password",
        action="store_true",
        help="a new random MQTT password for each node; the broker takes it beside the old one until the node "
        "confirms it (run where the broker's credentials folder is, as wsnav broker revoke)",
    )
    c.add_argument(
        "--mosquitto-config",
        type=Path,
        metavar="DIR",
        help="with --new-password on Mosquitto: the folder of `wsnav broker mosquitto-config --pending-passwords`",
    )
    _key_and_timeout(c, "signs and seals the configuration")
    c.set_defaults(func=config_command)

    g = fw_sub.add_parser(
        "logs",
        help="print running nodes' last log lines (each keeps its last 8 and sends them on a `log` command)",
    )
    operator_arguments(g)
    g.add_argument("--nodes", required=True, metavar="N1,N2", help="the nodes to ask, comma-separated")
    g.add_argument(
        "--timeout", type=float, default=10.0, metavar="S", help="wait this long for the answers (default 10)"
    )
    g.set_defaults(func=logs_command)

    a = fw_sub.add_parser(
        "fallback-ap",
        help="print each node's fallback access point (opened when it joins no known network): its name and "
        "WPA2 key, derived from the site's update key; nothing is sent",
    )
    a.add_argument(
        "--credentials", type=Path, required=True, metavar="FILE", help="the operator's operator.json"
    )
    a.add_argument("--nodes", required=True, metavar="N1,N2", help="the nodes, comma-separated")
    _update_key_argument(a, "the keys derive from")
    a.set_defaults(func=fallback_ap_command)


def _update_key_argument(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--update-key",
        type=Path,
        metavar="FILE",
        help=f"the site's update key that {what} (default: update.key beside --credentials, where "
        "wsnav broker credentials writes it)",
    )


def _key_and_timeout(p: argparse.ArgumentParser, what: str) -> None:
    _update_key_argument(p, what)
    p.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        metavar="S",
        help="give up on nodes not done by then (default 600)",
    )


def _node_ids(args: argparse.Namespace) -> list[str]:
    """--nodes as a list, checked."""
    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    if not nodes or len(set(nodes)) != len(nodes):
        raise CliError(f"--nodes {args.nodes!r}: give node ids, each once, separated by commas")
    return nodes


def _nodes(args: argparse.Namespace) -> list[str]:
    """--nodes as a list, checked, and --timeout checked."""
    nodes = _node_ids(args)
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise CliError(f"--timeout {args.timeout:g}: expected a positive number of seconds")
    return nodes


def _site_key(args: argparse.Namespace) -> str:
    """The site's update key from --update-key (or update.key beside --credentials)."""
    key_file = args.update_key or args.credentials.parent / UPDATE_KEY_FILE
    try:
        site_key = key_file.read_text().strip()
    except OSError as exc:
        raise CliError(
            f"{key_file}: cannot read the site's update key ({exc.strerror}); wsnav broker credentials makes it"
        ) from None
    if len(site_key) != 64 or any(c not in "0123456789abcdef" for c in site_key):
        raise CliError(f"{key_file}: not an update key (64 hex digits)")
    return site_key


def _send_and_follow(
    args: argparse.Namespace,
    link: OperatorLink,
    server: NodeTransfer,
    signatures: dict[str, str],
    command: NodeCommandName,
) -> list[str]:
    """Each node's `command` with its signature, then `server` (subscribed first) until all are done or failed
    or --timeout; the failures, one line each."""
    from wsnav.console.operator_commands import CommandError, node_command

    try:
        pubs = {n: node_command(link.site, n, command, manifest=sig) for n, sig in signatures.items()}
    except CommandError as exc:
        raise CliError(str(exc)) from None
    server.subscribe()
    for node, pub in pubs.items():
        if not link.bus.publish_confirmed(pub.topic, pub.payload):
            server.progress[node].error = f"{node}: the broker did not confirm the {command} command"
    return server.run(args.timeout)


def ota_command(args: argparse.Namespace) -> int:
    """Build, send each node its `update` signed with its key (derived from the site's update key: a node
    refuses an unsigned or wrongly signed manifest), serve the chunks with progress; exit 1 unless every node
    confirmed (ran the new version healthy for a while: firmware/ota.py)."""
    from wsnav.console.operator_link import connect
    from wsnav.firmware.ota import OtaError, OtaServer, make_update

    nodes = _nodes(args)
    with tempfile.TemporaryDirectory(prefix="wsnav-ota-") as tmp:
        try:
            update = make_update(Path(tmp), args.source)
        except (BuildError, OtaError) as exc:
            raise CliError(str(exc)) from None
    site_key = _site_key(args)
    m = update.manifest
    print(f"update {m.version}: {len(m.files)} files, {update.total} B (manifest {update.digest[:12]})")
    link = connect(args, "ota")
    try:
        signatures = {n: update.signature(node_update_key(site_key, n)) for n in nodes}
        server = OtaServer(link.bus, link.site.name, update, nodes)
        failures = _send_and_follow(args, link, server, signatures, "update")
    finally:
        link.bus.close()
    for line in failures:
        print(line, file=sys.stderr)
    done = len(nodes) - len(failures)
    print(f"{done} of {len(nodes)} nodes running {m.version}")
    return 1 if failures else 0


def _follow_on_new_broker(args: argparse.Namespace) -> OperatorLink | None:
    """The operator's login on --node-broker too, when it is another address: a node moved there confirms
    there. None (and one line saying so) when it cannot be reached from here with these credentials."""
    from wsnav.console.operator_link import connect

    if args.node_broker is None or tuple(args.node_broker) == tuple(args.broker):
        return None
    try:
        return connect(argparse.Namespace(**{**vars(args), "broker": args.node_broker}), "config")
    except CliError as exc:
        host, port = args.node_broker
        print(
            f"cannot follow the nodes on {host}:{port} ({exc}): a node that moves there is reported as not "
            "confirmed here; check it there with wsnav status"
        )
        return None


def config_command(args: argparse.Namespace) -> int:
    """Seal the settings for each node (its own key), send its `config`, serve them, wait until each has kept
    them or gone back (firmware/ota_config.py); exit 1 naming every node that did not keep them. With
    --new-password, each node's new password is pending at the broker before its command goes (PendingPasswords)."""
    from wsnav.console.operator_link import connect
    from wsnav.firmware.ota_config import ConfigError, ConfigServer, Settings, seal_for

    nodes = _nodes(args)
    wifi = None
    if args.wifi:
        lines = sys.stdin.read().split("\n")
        if len(lines) < 2 or not lines[0]:
            raise CliError("--wifi: give the SSID on the first line of stdin and the key on the second")
        wifi = (lines[0].rstrip("\r"), lines[1].rstrip("\r"))
    if args.mosquitto_config is not None and not args.new_password:
        raise CliError("--mosquitto-config goes with --new-password")
    try:  # the settings checked before anything is read (each node's own password goes in below)
        Settings(
            wifi=wifi, broker=args.node_broker, password="p" * 32 if args.new_password else None
        ).payload()
    except ConfigError as exc:
        raise CliError(str(exc)) from None
    passwords = PendingPasswords.new(args, nodes) if args.new_password else None
    site_key = _site_key(args)
    sealed: dict[str, bytes] = {}
    signatures: dict[str, str] = {}
    for n in nodes:
        password = passwords.new_of[n] if passwords is not None else None
        try:
            settings = Settings(wifi=wifi, broker=args.node_broker, password=password).payload()
        except ConfigError as exc:
            raise CliError(str(exc)) from None
        sealed[n], signatures[n] = seal_for(node_update_key(site_key, n), settings)
    what = (("Wi-Fi", wifi), ("broker", args.node_broker), ("MQTT password", passwords))
    print(f"configuration: new {' and '.join(k for k, v in what if v is not None)} for {len(nodes)} node(s)")
    link = connect(args, "config")
    new_broker = _follow_on_new_broker(args)
    try:
        if passwords is not None:
            passwords.add()
        server = ConfigServer(link.bus, link.site.name, sealed)
        if new_broker is not None:
            server.follow_on(new_broker.bus)
        failures = _send_and_follow(args, link, server, signatures, "config")
    finally:
        link.bus.close()
        if new_broker is not None:
            new_broker.bus.close()
    if passwords is not None:
        passwords.settle(server, link.site.spec)
    for line in failures:
        print(line, file=sys.stderr)
    print(f"{len(nodes) - len(failures)} of {len(nodes)} nodes kept the new configuration")
    return 1 if failures else 0


class PendingPasswords:
    """`--new-password`: each node's new password pending at the broker (amqtt: broker.pending in the credentials
    folder; Mosquitto: its pending-password plugin's file) while the node tries it, so neither password is ever
    refused to it; made its own once it confirms, withdrawn once it went back (broker/credentials.py)."""

    def __init__(self, folder: Path, mosquitto: Path | None, new_of: dict[str, str]) -> None:
        self.folder = folder
        self.mosquitto = mosquitto
        self.new_of = new_of

    @classmethod
    def new(cls, args: argparse.Namespace, nodes: list[str]) -> PendingPasswords:
        from wsnav.broker.credentials import PASSWORD_FILE, new_password

        folder = args.credentials.parent
        if not (folder / PASSWORD_FILE).exists():
            raise CliError(
                f"--new-password: no {PASSWORD_FILE} beside {args.credentials}: run it where the broker's "
                "credentials folder is"
            )
        return cls(folder, args.mosquitto_config, {n: new_password() for n in nodes})

    def add(self) -> None:
        """Every node's new password taken by the broker from now on, beside its own."""
        from wsnav.broker.credentials import add_pending
        from wsnav.broker.mosquitto.pending import add
        from wsnav.schemas.credentials import CredentialsError

        try:
            for node, password in self.new_of.items():
                add_pending(self.folder, node, password)
                if self.mosquitto is not None:
                    add(self.mosquitto, node, password)
        except CredentialsError as exc:
            raise CliError(str(exc)) from None

    def settle(self, server: NodeTransfer, spec: SiteFile) -> None:
        """Confirmed: the new password becomes the node's (`<node>.json`, the password files) and the old one
        is refused (on Mosquitto after its reload). Gone back or refused before trying it: the pending password
        is withdrawn. Neither (it may be trying it): both stay accepted, and a line says so."""
        from wsnav.broker.credentials import promote_pending, withdraw_pending
        from wsnav.broker.mosquitto.config import rewrite_passwords
        from wsnav.broker.mosquitto.pending import keep_only, withdraw
        from wsnav.schemas.credentials import CredentialsError

        promoted = False
        try:
            for node, password in self.new_of.items():
                prog = server.progress[node]
                if prog.done:
                    promote_pending(self.folder, node, password)
                    if self.mosquitto is not None:
                        keep_only(self.mosquitto, node, password)
                    promoted = True
                    when = "once Mosquitto reloads" if self.mosquitto is not None else "from now on"
                    print(
                        f"{node}: new MQTT password in {self.folder / (node + '.json')}, the old one refused {when}"
                    )
                elif prog.error is not None or not prog.started:
                    withdraw_pending(self.folder, node, password)
                    if self.mosquitto is not None:
                        withdraw(self.mosquitto, node, password)
                else:
                    print(
                        f"{node}: its old and new MQTT passwords both stay accepted (it may be trying the new "
                        "one): send it a new password again once it is back",
                        file=sys.stderr,
                    )
            if promoted and self.mosquitto is not None:
                path = rewrite_passwords(spec, self.folder, self.mosquitto)
                print(
                    f"wrote {path}: reload Mosquitto (sudo systemctl reload mosquitto) to refuse the old passwords"
                )
        except CredentialsError as exc:
            raise CliError(str(exc)) from None


def logs_command(args: argparse.Namespace) -> int:
    """Send each node a `log` command and print the lines it answers with (schemas.messages.NodeLog), node by
    node as they come, a character a terminal would act on shown escaped; exit 1 if a node did not answer within
    --timeout (offline: a command is not queued) or answered with a message the contract refuses (one line)."""
    import time

    from wsnav.console.operator_commands import CommandError, node_command
    from wsnav.console.operator_link import connect
    from wsnav.schemas import topics
    from wsnav.schemas.messages import NodeLog, PayloadError, parse_payload

    nodes = _nodes(args)
    link = connect(args, "logs")
    waiting = set(nodes)
    failures: list[str] = []
    try:
        try:
            pubs = {n: node_command(link.site, n, "log") for n in nodes}
        except CommandError as exc:
            raise CliError(str(exc)) from None
        for n in nodes:
            link.bus.subscribe(topics.node_log(link.site.name, n), qos=0)
        for n, pub in pubs.items():  # subscribed first: the answer comes at once
            if not link.bus.publish_confirmed(pub.topic, pub.payload):
                failures.append(f"{n}: the broker did not confirm the log command")
                waiting.discard(n)
        deadline = time.monotonic() + args.timeout
        while waiting and (left := deadline - time.monotonic()) > 0:
            link.bus.wait(left)
            for msg in link.bus.poll():
                parsed = topics.parse(msg.topic)
                if parsed is None or parsed.node not in waiting or msg.retain:
                    continue
                waiting.discard(parsed.node)
                try:
                    answer = parse_payload(NodeLog, msg.payload)
                except PayloadError as exc:
                    failures.append(f"{parsed.node}: its log message was refused: {exc}")
                    continue
                print(f"{parsed.node}: its last log lines ({len(answer.lines)})")
                for line in answer.lines:
                    print("  " + "".join(c if c.isprintable() else repr(c)[1:-1] for c in line))
    finally:
        link.bus.close()
    failures += [
        f"{n}: no answer within {args.timeout:g} s (offline? a command is not queued)"
        for n in nodes
        if n in waiting
    ]
    for line in failures:
        print(line, file=sys.stderr)
    return 1 if failures else 0


def fallback_ap_command(args: argparse.Namespace) -> int:
    """One line per node: its id, its access point's name and key (firmware/device/fallback_ap.py), for the
    installer who joins it with a phone to give a node that lost its network a new one."""
    import re

    from wsnav.schemas.ids import ID_PATTERN

    nodes = _node_ids(args)
    for n in nodes:
        if not re.match(ID_PATTERN, n):
            raise CliError(f"--nodes: {n!r} is not a node id")
    site_key = _site_key(args)
    for n in nodes:
        print(f"{n}  {fallback_ap_ssid(n)}  {fallback_ap_key(node_update_key(site_key, n))}")
    return 0
