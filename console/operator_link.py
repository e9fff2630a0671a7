"""The operator's connection to the site: site, credentials and broker checked, each problem one line."""

from __future__ import annotations

import argparse
import math
import os
import secrets
from dataclasses import dataclass

from wsnav.runtime.cli_support import CliError
from wsnav.runtime.clock import WallClock
from wsnav.runtime.login_copies import LoginCopies
from wsnav.runtime.mqtt_bus import BusError, MqttBus
from wsnav.schemas.credentials import (
    OPERATOR_TOOLS,
    Credentials,
    CredentialsError,
    credentials_for,
    tool_copies,
    tool_login,
)
from wsnav.schemas.site import Site, SiteError, load_site


@dataclass
class OperatorLink:
    site: Site
    credentials: Credentials
    bus: MqttBus
    clock: WallClock


def load_operator(args: argparse.Namespace) -> tuple[Site, Credentials]:
    try:
        site = load_site(args.site)
    except SiteError as exc:
        raise CliError(str(exc)) from None
    try:
        creds = credentials_for(args.credentials, role="operator", site=site.name, ids=["operator"])
    except CredentialsError as exc:
        raise CliError(str(exc)) from None
    return site, creds


def connect(args: argparse.Namespace, purpose: str) -> OperatorLink:
    """Connected as the tool's own login (`operator.watch`; every verb is `operator.command`), and as a copy of
    it no other copy on this host holds (`operator.watch.2`...), with a client id of its own: on Mosquitto, where
    a client id is its login, the console, watch and status, and two copies of one of them, no longer take each
    other over; on amqtt several consoles may run."""
    site, creds = load_operator(args)
    login = tool_login(creds, purpose if purpose in OPERATOR_TOOLS else "command")
    if not (math.isfinite(args.connect_timeout) and args.connect_timeout > 0):
        raise CliError(f"--connect-timeout {args.connect_timeout:g}: expected a positive number of seconds")
    clock = WallClock()
    host, port = args.broker
    try:
        bus = MqttBus(
            host,
            port,
            client_id=f"{login.username}-{purpose}-{os.getpid()}-{secrets.token_hex(3)}",
            username=login.username,
            password=login.password,
            clock=clock,
            tls_ca=args.tls_ca,
            logins=LoginCopies(tool_copies(login)),
        ).connect(timeout_s=args.connect_timeout)
    except BusError as exc:
        raise CliError(str(exc)) from None
    return OperatorLink(site, creds, bus, clock)
