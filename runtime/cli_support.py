"""What every subcommand shares: one-line errors instead of tracebacks, the HOST:PORT argument type, and the
broker arguments."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

if TYPE_CHECKING:
    from wsnav.runtime.mqtt_bus import MqttBus
    from wsnav.schemas.credentials import Credentials
    from wsnav.schemas.site import Site


class CliError(Exception):
    """A problem the user can fix; printed as one line on stderr, exit code 2."""


class Parser(argparse.ArgumentParser):
    """argparse, but a bad argument prints one line (`wsnav: error: ...`) rather than usage plus error."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def host_port(text: str) -> tuple[str, int]:
    """Parse HOST:PORT (IPv6 in brackets); argparse turns the ValueError into a one-line error."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


def add_broker_arguments(parser: argparse.ArgumentParser) -> None:
    """`--broker HOST:PORT` and `--tls-ca FILE`, the same on every command that logs in to the site's broker."""
    parser.add_argument("--broker", type=host_port, required=True, metavar="HOST:PORT")
    parser.add_argument(
        "--tls-ca",
        type=Path,
        metavar="FILE",
        help="connect over TLS (the broker's TLS port), trusting the CA in FILE (the site's ca.crt)",
    )


def refuse_bad_login(bus: MqttBus, timeout_s: float) -> None:
    """Wait up to `timeout_s` for the broker's first answer; a refused login is a one-line CliError (a wrong
    password is a set-up to fix, not an outage to ride out), no answer is an outage the reader rides out."""
    bus.wait_answered(timeout_s)
    if bus.refusal is not None:
        bus.abort()
        raise CliError(f"MQTT broker {bus.address} refused the login: {bus.refusal} (check the credentials)")


def add_state_dir_argument(parser: argparse.ArgumentParser) -> None:
    """`--state-dir DIR`, the same on every reader of zone states that can keep them across restarts."""
    parser.add_argument(
        "--state-dir",
        type=Path,
        metavar="DIR",
        help="keep the last known zone states in DIR (zones-<site>.json) and start from them, aged by the "
        "site's stale policy, when restarted (also with the broker down)",
    )


def fail(message: str) -> NoReturn:
    print(f"wsnav: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def read_robot_credentials(path: Path, site: Site) -> Credentials:
    """A robot's credentials file (from `wsnav broker credentials`), checked against the site; a problem is one
    CliError. Here, not in the agent, so the ROS bridges check a file without loading the agent and numba."""
    from wsnav.schemas.credentials import CredentialsError, credentials_for

    try:
        return credentials_for(path, role="robot", site=site.name, ids=[r.id for r in site.spec.robots])
    except CredentialsError as exc:
        raise CliError(str(exc)) from None
