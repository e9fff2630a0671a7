"""`wsnav broker run | credentials | mosquitto-config | mosquitto-restore | firewall | revoke | ha-discovery`."""

from __future__ import annotations

import argparse
import asyncio
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.broker.amqtt.gc_pacing import FREEZE_EVERY_S, REFRESH_EVERY_S
from wsnav.broker.identity_limits import (
    MAX_SUBSCRIPTIONS,
    NODE_PUBLISH_RATE,
    SESSION_EXPIRY_S,
    IdentityLimits,
)
from wsnav.runtime.cli_support import CliError, host_port

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser
    from wsnav.schemas.site_file import SiteFile

# The broker modules (and amqtt) are imported inside the commands: every `wsnav` call builds this parser.


def bind_address(text: str) -> tuple[str, int]:
    """HOST:PORT for a listener; port 0 means any free port (the ready line tells which)."""
    host, sep, port = text.rpartition(":")
    if sep and host and port == "0":
        return host.strip("[]"), 0
    return host_port(text)


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    broker = sub.add_parser(
        "broker", help="the site's MQTT broker: run it, make credentials, configure Mosquitto"
    )
    bsub = broker.add_subparsers(dest="broker_command", required=True, parser_class=type(broker))

    run = bsub.add_parser(
        "run", help="run the amqtt broker for a site (auth, ACL, persistent retained state)"
    )
    run.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    run.add_argument("--credentials", type=Path, required=True, help="folder written by `broker credentials`")
    run.add_argument(
        "--bind", type=bind_address, required=True, help="HOST:PORT of the MQTT/TCP listener (port 0: any)"
    )
    run.add_argument(
        "--data", type=Path, help="folder for persistent retained messages (default: memory only)"
    )
    run.add_argument(
        "--flush-interval", type=float, default=0.2, help="seconds; retained writes lag at most this"
    )
    run.add_argument(
        "--sync", choices=["normal", "full"], default="normal", help="full: survive power cuts too"
    )
    run.add_argument(
        "--ws-bind", type=bind_address, help="HOST:PORT of an optional MQTT-over-WebSocket listener"
    )
    run.add_argument("--tls-bind", type=bind_address, help="HOST:PORT of an optional MQTT/TLS listener")
    run.add_argument("--certfile", type=Path, help="TLS certificate chain (PEM), with --tls-bind")
    run.add_argument("--keyfile", type=Path, help="TLS private key (PEM), with --tls-bind")
    run.add_argument("--cafile", type=Path, help="CA bundle to verify client certificates, with --tls-bind")
    run.add_argument(
        "--max-connections",
        type=int,
        default=0,
        help="all listeners together; 0 = as many as the open-file limit allows",
    )
    run.add_argument(
        "--connect-timeout", type=float, default=5.0, help="seconds a new socket has to send its CONNECT"
    )
    run.add_argument(
        "--max-packet-bytes", type=int, default=32768, help="bigger MQTT packets close the connection"
    )
    run.add_argument(
        "--gc-freeze",
        type=float,
        default=FREEZE_EVERY_S,
        help="seconds between freezing the objects alive out of garbage collections (0: never)",
    )
    run.add_argument(
        "--gc-refresh",
        type=float,
        default=REFRESH_EVERY_S,
        help="seconds between full collections reclaiming what ended connections left (skipped when none "
        "ended: a steady site never stalls for one)",
    )
    run.add_argument(
        "--max-subscriptions",
        type=int,
        default=MAX_SUBSCRIPTIONS,
        help="topic filters one session may hold; more are refused",
    )
    run.add_argument(
        "--node-publish-rate",
        type=float,
        default=NODE_PUBLISH_RATE,
        help="messages per second a node may publish (bursts of 100); faster ones are read at this rate "
        "(TCP backpressure), nothing is dropped; 0 = no limit",
    )
    run.add_argument(
        "--session-expiry",
        type=float,
        default=SESSION_EXPIRY_S,
        help="seconds a disconnected persistent session is kept",
    )
    run.set_defaults(func=run_command)

    creds = bsub.add_parser("credentials", help="per-id credentials files and the broker's password file")
    creds.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    creds.add_argument("--out", type=Path, required=True, help="credentials folder (created 0700)")
    creds.add_argument(
        "--broker", type=host_port, help="HOST:PORT the devices connect to (kept when omitted)"
    )
    creds.add_argument("--wifi-ssid", help="Wi-Fi network written into every node's config")
    creds.add_argument(
        "--wifi-password",
        help="Wi-Fi password written into every node's config; `-` reads it from the first line of stdin "
        "(kept out of the process list and the shell history)",
    )
    creds.set_defaults(func=credentials_command)

    mosq = bsub.add_parser("mosquitto-config", help="mosquitto.conf, password and ACL files: the same model")
    mosq.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    mosq.add_argument(
        "--credentials", type=Path, required=True, help="folder written by `broker credentials`"
    )
    mosq.add_argument("--out", type=Path, required=True, help="folder for the three files (created 0700)")
    mosq.add_argument(
        "--bind", type=host_port, default=("0.0.0.0", 1883), help="HOST:PORT (default 0.0.0.0:1883)"
    )
    mosq.add_argument(
        "--data",
        type=Path,
        default=Path("/var/lib/mosquitto"),
        help="persistence folder, created if missing (and given to --user)",
    )
    mosq.add_argument(
        "--user",
        help="system user Mosquitto drops to when started as root; the files and --data are given to it "
        "(default: none written: Mosquitto then drops to `mosquitto`, which cannot read root's 0600 files)",
    )
    mosq.add_argument(
        "--shared-client-ids",
        action="store_true",
        help="let one identity hold several connections (simulation stacks); then any identity can kick "
        "another's connection by reusing its client id",
    )
    mosq.add_argument(
        "--store-guard",
        action="store_true",
        help="build wsnav's Mosquitto plugin into --out and load it: operator blocks journaled (fdatasync) "
        "before their PUBACK and put back at start, so a power cut loses none; a full disk or a cut-short store "
        "logged as an ERROR within a second (needs gcc, mosquitto-dev and libmosquitto-dev)",
    )
    mosq.add_argument("--tls-bind", type=host_port, help="HOST:PORT of an MQTT/TLS listener (as on amqtt)")
    mosq.add_argument("--certfile", type=Path, help="TLS certificate chain (PEM), with --tls-bind")
    mosq.add_argument("--keyfile", type=Path, help="TLS private key (PEM), with --tls-bind")
    mosq.set_defaults(func=mosquitto_command)

    restore = bsub.add_parser(
        "mosquitto-restore",
        help="before Mosquitto starts (ExecStartPre): put back the last whole store if its store was cut short",
    )
    restore.add_argument(
        "--data", type=Path, default=Path("/var/lib/mosquitto"), help="Mosquitto's persistence_location"
    )
    restore.set_defaults(func=mosquitto_restore_command)

    firewall = bsub.add_parser(
        "firewall",
        help="an nftables file resetting the connections of a node address that sends the MQTT port more "
        "bytes a second than its rate (Mosquitto's only defence against a flooding node)",
    )
    firewall.add_argument("--nodes-subnet", required=True, help="the nodes' network, e.g. 192.168.10.0/24")
    firewall.add_argument("--port", type=int, default=1883, help="the nodes' MQTT port (default 1883)")
    firewall.add_argument(
        "--rate", type=int, default=4, metavar="KBYTES", help="per node a second (default 4)"
    )
    firewall.add_argument("--burst", type=int, default=16, metavar="KBYTES", help="per node (default 16)")
    firewall.set_defaults(func=firewall_command)

    revoke = bsub.add_parser(
        "revoke",
        help="give ids new passwords (the old ones stop working without a restart) and clear their retained "
        "messages",
    )
    revoke.add_argument("ids", nargs="+", metavar="ID", help="node, robot, operator or dashboard ids")
    revoke.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    revoke.add_argument("--credentials", type=Path, required=True, help="the site's credentials folder")
    revoke.add_argument(
        "--mosquitto-config",
        type=Path,
        metavar="DIR",
        help="also rewrite this `mosquitto-config` folder's password file (then: systemctl reload mosquitto)",
    )
    revoke.add_argument(
        "--broker",
        type=host_port,
        metavar="HOST:PORT",
        help="the running broker: log in with the new password, clear the ids' retained messages, check the "
        "old password is refused",
    )
    revoke.add_argument("--tls-ca", type=Path, metavar="FILE", help="with --broker: its TLS port's CA")
    revoke.add_argument(
        "--wait", type=float, default=30.0, metavar="S", help="for the broker to take the new password"
    )
    revoke.set_defaults(func=revoke_command)

    ha = bsub.add_parser(
        "ha-discovery", help="publish Home Assistant MQTT discovery for the site's zones and nodes (retained)"
    )
    ha.add_argument("--site", type=Path, required=True, help="site directory or site.yaml")
    ha.add_argument("--broker", type=host_port, required=True, help="HOST:PORT of the site's broker")
    ha.add_argument(
        "--credentials", type=Path, required=True, help="the operator's credentials file (operator.json)"
    )
    ha.add_argument("--prefix", default="homeassistant", help="Home Assistant's discovery prefix")
    ha.add_argument("--dry-run", action="store_true", help="print the topics and payloads, publish nothing")
    ha.set_defaults(func=ha_discovery_command)


def _site(path: Path) -> SiteFile:
    """The site file alone: the broker needs no map (nor numpy and Pillow to read one)."""
    from wsnav.schemas.site import SiteError, load_site_file

    try:
        return load_site_file(path)
    except SiteError as exc:
        raise CliError(str(exc)) from None


def run_command(args: argparse.Namespace) -> int:
    from wsnav.broker.amqtt.config import BrokerOptions, TlsListener
    from wsnav.broker.amqtt.server import BrokerStartError, RunningBroker, serve

    spec = _site(args.site)
    tls = None
    if args.tls_bind is not None:
        if args.certfile is None or args.keyfile is None:
            raise CliError("--tls-bind needs --certfile and --keyfile")
        for path in (args.certfile, args.keyfile, args.cafile):
            if path is not None and not path.is_file():
                raise CliError(f"{path}: no such file")
        tls = TlsListener(args.tls_bind, args.certfile, args.keyfile, args.cafile)
    if args.flush_interval < 0:
        raise CliError("--flush-interval must be >= 0")
    if not 0 < args.connect_timeout <= 3600:
        raise CliError("--connect-timeout must be > 0 and <= 3600 seconds")
    if not 1024 <= args.max_packet_bytes <= 268_435_455:
        raise CliError("--max-packet-bytes must be between 1024 and 268435455")
    if args.max_connections < 0:
        raise CliError("--max-connections must be >= 0")
    if not 0 <= args.gc_freeze <= 3600:
        raise CliError("--gc-freeze must be >= 0 and <= 3600 seconds")
    if not 1 <= args.gc_refresh <= 86400:
        raise CliError("--gc-refresh must be >= 1 and <= 86400 seconds")
    if not 1 <= args.max_subscriptions <= 100_000:
        raise CliError("--max-subscriptions must be between 1 and 100000")
    if not 0 <= args.node_publish_rate <= 100_000:
        raise CliError("--node-publish-rate must be >= 0 and <= 100000 per second")
    if not 1 <= args.session_expiry <= 365 * 86400:
        raise CliError("--session-expiry must be between 1 second and a year")
    limits = IdentityLimits(
        max_subscriptions=args.max_subscriptions,
        session_expiry_s=math.ceil(args.session_expiry),
        node_publish_rate=args.node_publish_rate or None,
    )
    options = BrokerOptions(
        bind=args.bind,
        data_dir=args.data,
        flush_interval_s=args.flush_interval,
        synchronous=args.sync.upper(),
        ws_bind=args.ws_bind,
        tls=tls,
        max_connections=args.max_connections,
        connect_timeout_s=args.connect_timeout,
        max_packet_bytes=args.max_packet_bytes,
        gc_freeze_s=args.gc_freeze,
        gc_refresh_s=args.gc_refresh,
        limits=limits,
    )

    def ready(running: RunningBroker) -> None:
        print(running.ready_line(), flush=True)
        missing = _ids_without_password(spec, args.credentials)
        if missing:
            print(
                f"wsnav: note: no password for {', '.join(missing)} in {args.credentials}: they cannot log in "
                "(rerun `wsnav broker credentials`)",
                file=sys.stderr,
            )
        if args.data is None:
            print("wsnav: note: no --data folder: retained messages are kept in memory only", file=sys.stderr)

    try:
        asyncio.run(serve(spec, args.credentials, options, ready))
    except BrokerStartError as exc:
        raise CliError(str(exc)) from None
    print("broker stopped", flush=True)
    return 0


def _ids_without_password(spec: SiteFile, credentials: Path) -> list[str]:
    from wsnav.broker.credentials import PASSWORD_FILE, read_password_file, site_ids
    from wsnav.schemas.credentials import CredentialsError

    try:
        users = read_password_file(credentials / PASSWORD_FILE)
    except CredentialsError:
        return []
    return [ident for ident in site_ids(spec) if ident not in users]


def credentials_command(args: argparse.Namespace) -> int:
    from wsnav.broker.credentials import write_credentials
    from wsnav.schemas.credentials import CredentialsError

    spec = _site(args.site)
    wifi_password = args.wifi_password
    if wifi_password == "-":
        wifi_password = sys.stdin.readline().rstrip("\r\n")
        if not wifi_password:
            raise CliError("--wifi-password -: stdin gave no password (one line expected)")
    try:
        report = write_credentials(spec, args.out, args.broker, args.wifi_ssid, wifi_password)
    except CredentialsError as exc:
        raise CliError(str(exc)) from None
    for ident in report.created:
        print(f"{ident}: new credentials")
    for ident in report.kept:
        print(f"{ident}: kept existing password")
    for ident in report.stale:
        print(
            f"{ident}.json: {ident} is no longer in the site: left in place, removed from the password file"
        )
    print(f"wrote {args.out}/ ({len(report.created) + len(report.kept)} ids)")
    return 0


def mosquitto_command(args: argparse.Namespace) -> int:
    from wsnav.broker.mosquitto.config import MosquittoOptions, MosquittoTls, write_mosquitto_config
    from wsnav.broker.mosquitto.plugin import PluginBuildError, build_plugin
    from wsnav.schemas.credentials import CredentialsError

    spec = _site(args.site)
    tls = None
    if args.tls_bind is not None or args.certfile is not None or args.keyfile is not None:
        if args.tls_bind is None or args.certfile is None or args.keyfile is None:
            raise CliError("--tls-bind, --certfile and --keyfile go together")
        for path in (args.certfile, args.keyfile):
            if not path.is_file():
                raise CliError(f"{path}: no such file")
        tls = MosquittoTls(args.tls_bind, args.certfile.resolve(), args.keyfile.resolve())
    store_guard = None
    if args.store_guard:
        try:
            store_guard = build_plugin(args.out.resolve())
        except PluginBuildError as exc:
            raise CliError(f"--store-guard: {exc}") from None
    options = MosquittoOptions(
        bind=args.bind,
        data_dir=args.data.resolve(),
        user=args.user,
        bind_client_ids=not args.shared_client_ids,
        tls=tls,
        store_guard=store_guard,
    )
    try:
        files = write_mosquitto_config(spec, args.credentials, args.out, options)
    except CredentialsError as exc:
        raise CliError(str(exc)) from None
    if store_guard is not None:
        print(f"built {store_guard}")
    for path in files:
        print(f"wrote {path}")
    print(f"run: mosquitto -c {files[0]}")
    return 0


def firewall_command(args: argparse.Namespace) -> int:
    from wsnav.broker.mosquitto.firewall import nft_rules

    try:
        print(nft_rules(args.nodes_subnet, args.port, args.rate, args.burst), end="")
    except ValueError as exc:
        raise CliError(str(exc)) from None
    return 0


def mosquitto_restore_command(args: argparse.Namespace) -> int:
    """Never stops the start: a Mosquitto without its retained messages still serves the site (exit 1 is for
    the log's sake; the unit's `ExecStartPre=-` ignores it)."""
    from wsnav.broker.mosquitto.store import restore

    try:
        ok, line = restore(args.data)
    except OSError as exc:
        raise CliError(f"{args.data}: cannot restore the store: {exc.strerror}") from None
    print(line, file=sys.stdout if ok and not line.startswith("ERROR") else sys.stderr)
    return 0 if ok else 1


def revoke_command(args: argparse.Namespace) -> int:
    from wsnav.broker.credentials import site_ids, write_credentials
    from wsnav.broker.mosquitto.config import rewrite_passwords
    from wsnav.broker.revocation import clear_retained
    from wsnav.schemas.credentials import CredentialsError, load_credentials

    spec = _site(args.site)
    unknown = sorted(set(args.ids) - set(site_ids(spec)))
    if unknown:
        raise CliError(f"not ids of site {spec.name}: {', '.join(unknown)}")
    if not 0 < args.wait <= 3600:
        raise CliError("--wait must be > 0 and <= 3600 seconds")
    try:
        old = {ident: load_credentials(args.credentials / f"{ident}.json") for ident in args.ids}
        write_credentials(spec, args.credentials, renew=frozenset(args.ids))
        new = {ident: load_credentials(args.credentials / f"{ident}.json") for ident in args.ids}
        for ident in args.ids:
            print(f"{ident}: new password in {args.credentials / (ident + '.json')} (give it to the device)")
        if args.mosquitto_config is not None:
            path = rewrite_passwords(spec, args.credentials, args.mosquitto_config)
            print(f"wrote {path}: reload Mosquitto now (sudo systemctl reload mosquitto)", flush=True)
    except CredentialsError as exc:
        raise CliError(str(exc)) from None
    if args.broker is None:
        print("no --broker: the ids' retained messages were left on the broker")
        return 0
    failed = False
    for ident in args.ids:
        done = clear_retained(spec, args.broker, new[ident], old[ident], args.wait, args.tls_ca)
        if done.error is not None:
            print(f"{ident}: {done.error}", file=sys.stderr)
            failed = True
            continue
        cleared = ", ".join(done.cleared) or "no topics of its own"
        print(f"{ident}: cleared {cleared}")
        if not done.old_refused:
            print(f"{ident}: the broker still accepts the OLD password", file=sys.stderr)
            failed = True
    return 1 if failed else 0


def ha_discovery_command(args: argparse.Namespace) -> int:
    from wsnav.broker.ha_discovery import discovery_messages

    spec = _site(args.site)
    if not args.prefix or any(c in args.prefix for c in "+#") or args.prefix.strip("/") != args.prefix:
        raise CliError(f"--prefix {args.prefix!r}: a topic prefix without wildcards or outer slashes")
    messages = discovery_messages(spec, args.prefix)
    if args.dry_run:
        for topic, payload in messages:
            print(topic, payload.decode())
        return 0
    import time

    from wsnav.runtime.mqtt_bus import BusError, connect_with_credentials
    from wsnav.schemas.credentials import CredentialsError, load_credentials, tool_login

    host, port = args.broker
    try:
        creds = load_credentials(args.credentials)
        bus = connect_with_credentials(host, port, tool_login(creds, "ha-discovery"), copies=True)
    except (CredentialsError, BusError) as exc:
        raise CliError(str(exc)) from None
    # Read them back: a broker drops a publish its ACL refuses without telling the publisher.
    missing = dict(messages)
    try:
        bus.subscribe(f"{args.prefix}/binary_sensor/wsnav_{spec.name}/#")
        for topic, payload in messages:
            bus.publish(topic, payload, retain=True)
        deadline = time.monotonic() + 10.0
        while missing and bus.wait(max(0.0, deadline - time.monotonic())):
            for msg in bus.poll():
                if missing.get(msg.topic) == msg.payload:
                    del missing[msg.topic]
    finally:
        bus.close()
    if missing:
        raise CliError(
            f"{len(missing)} of {len(messages)} discovery configs did not come back from the broker (first: "
            f"{next(iter(missing))}): may {creds.username!r} publish and read {args.prefix}/#?"
        )
    print(f"published {len(messages)} discovery configs under {args.prefix}/ (retained)")
    return 0
