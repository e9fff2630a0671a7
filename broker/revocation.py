"""Revoking a credential without a restart: a new password, the old one refused, its retained messages gone.

`wsnav broker revoke ID` gives ID a new password in the credentials folder (and in a Mosquitto configuration's
password file, when given). The amqtt broker reads its password file again when it changes and closes the
identity's connections (wsnav.broker.amqtt.patch); Mosquitto does so on SIGHUP (`systemctl reload mosquitto`).
Then, with `--broker`, the command logs in with the new password and clears what the identity left retained
on its own topics (a node's zone state, status and diagnostics; a robot's status), so no robot or console acts
on a stolen credential's last word, and checks that the old password is refused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from wsnav.broker.acl import site_rules
from wsnav.runtime.mqtt_bus import BusError, connect_with_credentials
from wsnav.schemas.credentials import OPERATOR_TOOLS, Credentials, tool_copies, tool_login
from wsnav.schemas.site_file import SiteFile

SETTLE_S = 1.0
"""After the new password is accepted: time for the broker to close the old connections (their wills go out
first, and are cleared with the rest)."""


@dataclass
class Cleanup:
    """What `clear_retained` did for one identity."""

    ident: str
    cleared: list[str] = field(default_factory=list)
    old_refused: bool | None = None
    error: str | None = None


def own_topics(spec: SiteFile, ident: str) -> list[str]:
    """The exact topics `ident` may publish (wildcard rules, the operator's, are not an identity's own)."""
    return [t for t in site_rules(spec).publish.get(ident, []) if "+" not in t and "#" not in t]


def clear_retained(
    spec: SiteFile,
    broker: tuple[str, int],
    new: Credentials,
    old: Credentials,
    wait_s: float = 20.0,
    tls_ca: Path | None = None,
) -> Cleanup:
    """Log in with `new` (retrying until the broker has it, at most `wait_s`), clear the identity's retained
    messages, and try `old` once (it must be refused)."""
    result = Cleanup(new.username)
    host, port = broker
    deadline = time.monotonic() + wait_s
    while True:
        try:
            bus = connect_with_credentials(host, port, new, timeout_s=5.0, tls_ca=tls_ca)
            break
        except BusError as exc:
            if time.monotonic() >= deadline:
                result.error = f"the broker did not take the new password within {wait_s:g} s ({exc})"
                return result
            time.sleep(0.5)
    try:
        time.sleep(SETTLE_S)
        tools = [tool_login(new, tool) for tool in OPERATOR_TOOLS] if new.role == "operator" else []
        for login in [new.model_copy(update={"username": c}) for tool in tools for c in tool_copies(tool)]:
            # Mosquitto closes a connection of the old password only when its client id (= login) is taken over
            connect_with_credentials(host, port, login, timeout_s=5.0, tls_ca=tls_ca).close()
        for topic in own_topics(spec, new.username):
            if not bus.publish_confirmed(topic, b"", retain=True):
                result.error = f"no PUBACK for clearing {topic}"
                return result
            result.cleared.append(topic)
    finally:
        bus.close()
    try:
        probe = f"{old.username}-revoked"
        connect_with_credentials(host, port, old, client_id=probe, timeout_s=5.0, tls_ca=tls_ca).close()
        result.old_refused = False
    except BusError as exc:
        result.old_refused = "refused" in str(exc)
    return result
