"""`wsnav console`: the web app on uvicorn, fed by one operator MQTT connection that reconnects by itself."""

from __future__ import annotations

import argparse
import sqlite3
import sys
from pathlib import Path

import uvicorn

from wsnav.console.alerts import AckStore, AlertBoard
from wsnav.console.auth import Authenticator, open_store
from wsnav.console.block_store import BlockStore, blocks_path
from wsnav.console.event_log import EventLog, log_path
from wsnav.console.live_state import LiveState
from wsnav.console.operator_link import connect
from wsnav.console.site_view import SiteView
from wsnav.console.web_app import ConsoleApp
from wsnav.runtime.cli_support import CliError


def open_event_log(state_dir: Path, site: str) -> EventLog | None:
    try:
        return EventLog(log_path(state_dir, site))
    except (OSError, sqlite3.Error) as exc:
        print(f"console: no event log ({exc}): events are shown, not kept", file=sys.stderr, flush=True)
        return None


def open_alerts(state_dir: Path, site: str, now: float) -> AlertBoard:
    """Alerts whose acknowledgements are kept beside the event log (in its file)."""
    try:
        return AlertBoard(AckStore(log_path(state_dir, site), now))
    except (OSError, sqlite3.Error) as exc:
        print(f"console: acknowledgements not kept ({exc}): alerts are shown", file=sys.stderr, flush=True)
        return AlertBoard()


def open_block_store(state_dir: Path, site: str) -> BlockStore | None:
    try:
        return BlockStore(blocks_path(state_dir, site))
    except (OSError, sqlite3.Error) as exc:
        print(
            f"console: no block store ({exc}): operator blocks are kept only while this console runs",
            file=sys.stderr,
            flush=True,
        )
        return None


def console_command(args: argparse.Namespace) -> int:
    host, port = args.bind
    link = connect(args, "console")
    live = LiveState(
        SiteView(link.site),
        link.bus,
        link.clock,
        open_event_log(args.state_dir, link.site.name),
        open_alerts(args.state_dir, link.site.name, link.clock.now()),
        open_block_store(args.state_dir, link.site.name),
    )
    app = ConsoleApp(
        link.site,
        live,
        link.bus,
        link.clock,
        Authenticator(
            link.credentials.username,
            link.credentials.password,
            open_store(args.state_dir / f"console-{link.site.name}.sqlite", link.credentials.password),
        ),
    )
    live.start()
    config = uvicorn.Config(
        app.app,
        host=host,
        port=port,
        log_level="warning",
        access_log=False,
        lifespan="off",
        timeout_graceful_shutdown=2,  # open pages' event streams never end by themselves
    )
    server = uvicorn.Server(config)
    shown = f"[{host}]" if ":" in host else host
    print(
        f"console: http://{shown}:{port}/ (site {link.site.name}; log in as {link.credentials.username})",
        flush=True,
    )
    if host not in ("127.0.0.1", "::1", "localhost"):
        print(
            f"console: listening on {host}, not only loopback: put it behind TLS", file=sys.stderr, flush=True
        )
    try:
        server.run()
        if not server.started:
            raise CliError(f"cannot listen on {shown}:{port} (in use, or not an address of this host)")
    finally:
        live.stop()
        link.bus.close()
    return 0
