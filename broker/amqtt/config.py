"""The amqtt broker configuration generated from a site and its credentials folder.

Only our own plugins are loaded (auth, ACL, retained store): amqtt's default AnonymousAuthPlugin admits any
client that sends a username even with `allow_anonymous: false`, and its ACL plugin has no per-filter subscribe
rules. The connection cap is ours too (wsnav.broker.amqtt.admission): amqtt's `max_connections` makes new sockets wait
behind idle ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from wsnav.broker.acl import site_rules
from wsnav.broker.amqtt.gc_pacing import REFRESH_EVERY_S
from wsnav.broker.credentials import PASSWORD_FILE, site_ids
from wsnav.broker.identity_limits import MAX_PACKET_BYTES, IdentityLimits
from wsnav.schemas.site_file import SiteFile


@dataclass(frozen=True)
class TlsListener:
    bind: tuple[str, int]
    certfile: Path
    keyfile: Path
    cafile: Path | None = None


@dataclass(frozen=True)
class BrokerOptions:
    """Everything `wsnav broker run` (or the embedded helper) decides besides the site and credentials."""

    bind: tuple[str, int] = ("127.0.0.1", 1883)
    data_dir: Path | None = None
    """Where retained messages persist; None keeps them in memory only."""
    flush_interval_s: float = 0.2
    synchronous: str = "NORMAL"
    ws_bind: tuple[str, int] | None = None
    tls: TlsListener | None = None
    max_connections: int = 0
    """0: as many as the open-file limit allows (wsnav.broker.amqtt.admission keeps a reserve)."""
    connect_timeout_s: float = 5.0
    """A socket that has not sent a whole CONNECT by then is closed."""
    max_packet_bytes: int = MAX_PACKET_BYTES
    """Bigger packets end the connection (and are never stored or delivered)."""
    gc_freeze_s: float = 0.0
    """How often every object alive is frozen out of garbage collections (wsnav.broker.amqtt.gc_pacing); 0: never. The
    collector is the whole process's: `wsnav broker run` turns it on, a broker embedded in another program not."""
    gc_refresh_s: float = REFRESH_EVERY_S
    """How often, while freezing, one full collection reclaims frozen garbage, if a connection ended since the
    last one (a steady site never needs it; wsnav.broker.amqtt.gc_pacing)."""
    limits: IdentityLimits = field(default_factory=IdentityLimits)
    """Subscriptions, parked sessions and a node's publish rate per identity (wsnav.broker.identity_limits)."""


def bind_text(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def amqtt_config(spec: SiteFile, credentials_dir: Path, options: BrokerOptions) -> dict[str, Any]:
    """The dict for `amqtt.broker.Broker(config)`: listeners, our plugins, and persistence."""
    rules = site_rules(spec)
    listeners: dict[str, dict[str, Any]] = {
        "default": {
            "type": "tcp",
            "bind": bind_text(*options.bind),
        }
    }
    if options.ws_bind is not None:
        listeners["ws"] = {"type": "ws", "bind": bind_text(*options.ws_bind)}
    if options.tls is not None:
        tls: dict[str, Any] = {
            "type": "tcp",
            "bind": bind_text(*options.tls.bind),
            "ssl": True,
            "certfile": str(options.tls.certfile),
            "keyfile": str(options.tls.keyfile),
        }
        if options.tls.cafile is not None:
            tls["cafile"] = str(options.tls.cafile)
        listeners["tls"] = tls
    plugins: dict[str, Any] = {
        "wsnav.broker.amqtt.auth.WsnavAuthPlugin": {
            "password_file": str(credentials_dir / PASSWORD_FILE),
            "publish": rules.publish,
            "reserved_client_ids": site_ids(spec),
        },
        "wsnav.broker.acl.WsnavAclPlugin": {"publish": rules.publish, "subscribe": rules.subscribe},
    }
    if options.data_dir is not None:
        plugins["wsnav.broker.amqtt.retained_store.RetainedStorePlugin"] = {
            "data_dir": str(options.data_dir),
            "flush_interval_s": options.flush_interval_s,
            "synchronous": options.synchronous,
        }
    return {
        "listeners": listeners,
        "plugins": plugins,
        "session_expiry_interval": options.limits.session_expiry_s,
    }
