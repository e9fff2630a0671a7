"""`wsnav firmware ota`: the app of running nodes updated over MQTT, as the site's operator.

Here, not in firmware/cli.py: it logs in as the operator (`wsnav node-command`'s connection and command,
console/operator_link.py and console/operator_commands.py), and the firmware component does not import the console
(tests/test_component_imports.py). The transfer itself is firmware/ota.py.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.firmware.build import DEVICE, BuildError
from wsnav.runtime.cli_support import CliError
from wsnav.schemas.credentials import UPDATE_KEY_FILE, node_update_key

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser


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
    o.add_argument(
        "--update-key",
        type=Path,
        metavar="FILE",
        help="the site's update key that signs the update (default: update.key beside --credentials, where "
        "wsnav broker credentials writes it)",
    )
    o.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        metavar="S",
        help="give up on nodes not done by then (default 600)",
    )
    o.set_defaults(func=ota_command)


def ota_command(args: argparse.Namespace) -> int:
    """Build, send each node its `update` signed with its key (derived from the site's update key: a node
    refuses an unsigned or wrongly signed manifest), serve the chunks with progress; exit 1 unless every node
    confirmed (ran the new version healthy for a while: firmware/ota.py)."""
    from wsnav.console.operator_commands import CommandError, node_command
    from wsnav.console.operator_link import connect
    from wsnav.firmware.ota import OtaError, OtaServer, make_update

    nodes = [n.strip() for n in args.nodes.split(",") if n.strip()]
    if not nodes or len(set(nodes)) != len(nodes):
        raise CliError(f"--nodes {args.nodes!r}: give node ids, each once, separated by commas")
    if not (math.isfinite(args.timeout) and args.timeout > 0):
        raise CliError(f"--timeout {args.timeout:g}: expected a positive number of seconds")
    with tempfile.TemporaryDirectory(prefix="wsnav-ota-") as tmp:
        try:
            update = make_update(Path(tmp), args.source)
        except (BuildError, OtaError) as exc:
            raise CliError(str(exc)) from None
    key_file = args.update_key or args.credentials.parent / UPDATE_KEY_FILE
    try:
        site_key = key_file.read_text().strip()
    except OSError as exc:
        raise CliError(
            f"{key_file}: cannot read the site's update key ({exc.strerror}); wsnav broker credentials makes it"
        ) from None
    if len(site_key) != 64 or any(c not in "0123456789abcdef" for c in site_key):
        raise CliError(f"{key_file}: not an update key (64 hex digits)")
    m = update.manifest
    print(f"update {m.version}: {len(m.files)} files, {update.total} B (manifest {update.digest[:12]})")
    link = connect(args, "ota")
    try:
        try:
            pubs = [
                node_command(link.site, n, "update", manifest=update.signature(node_update_key(site_key, n)))
                for n in nodes
            ]
        except CommandError as exc:
            raise CliError(str(exc)) from None
        server = OtaServer(link.bus, link.site.name, update, nodes)
        server.subscribe()
        failures: list[str] = []
        for node, pub in zip(nodes, pubs, strict=True):
            if not link.bus.publish_confirmed(pub.topic, pub.payload):
                server.progress[node].error = f"{node}: the broker did not confirm the update command"
        failures = server.run(args.timeout)
    finally:
        link.bus.close()
    for line in failures:
        print(line, file=sys.stderr)
    done = len(nodes) - len(failures)
    print(f"{done} of {len(nodes)} nodes running {m.version}")
    return 1 if failures else 0
