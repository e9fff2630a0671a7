"""amqtt authentication: argon2 password file, no anonymous clients, no borrowed identities.

Replaces amqtt 0.12.1's AnonymousAuthPlugin, which admits any client that merely sends a username even with
`allow_anonymous: false` (docs/broker-amqtt.md).
A connect is refused when:
- there is no username, the user is unknown or the password is wrong;
- the client id names another site id (client ids also live in their identity's namespace, see
  wsnav.broker.amqtt.patch.session_key, so this is a clear early refusal of a misconfigured device rather than the
  only guard);
- the last-will topic is not one the user may publish (else a will could bypass the ACL, which amqtt does not
  check for wills). Mosquitto 2 refuses such a will the same way.
A successful verification is remembered as an HMAC under a per-process key, so reconnect storms do not pay the
argon2 cost again; argon2 itself runs in a worker thread so the event loop keeps serving other clients.
The password file is read again when it changes (`wsnav broker revoke`): a renewed password works at the next
login and the old one no longer does, without a restart (the broker drops the identity's connections, patch.py).
A node changing its password (`wsnav firmware config --new-password`) logs in with either its own or a pending one (the
PENDING_FILE beside the password file, read again when it changes too) until it confirms the new one.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import secrets
from dataclasses import dataclass, field
from pathlib import Path

from amqtt.contexts import BaseContext
from amqtt.plugins.base import BaseAuthPlugin
from amqtt.session import Session

from wsnav.broker.acl import AclRules
from wsnav.broker.credentials import (
    PENDING_FILE,
    file_stamp,
    read_password_file,
    read_pending_file,
    verify_password,
)
from wsnav.schemas.credentials import CredentialsError


class WsnavAuthPlugin(BaseAuthPlugin):
    @dataclass
    class Config(BaseAuthPlugin.Config):
        password_file: str = ""
        publish: dict[str, list[str]] = field(default_factory=dict)
        """The ACL's publish rules, to vet last-will topics."""
        reserved_client_ids: list[str] = field(default_factory=list)
        """Client ids only the user of the same name may use."""

    def __init__(self, context: BaseContext) -> None:
        super().__init__(context)
        config = self.context.config
        assert isinstance(config, WsnavAuthPlugin.Config)
        self._path = Path(config.password_file)
        self._hashes = read_password_file(self._path)
        self._stamp = file_stamp(self._path)
        self._pending_path = self._path.parent / PENDING_FILE
        self._pending = read_pending_file(self._pending_path)
        self._pending_stamp = file_stamp(self._pending_path)
        self._rules = AclRules(publish=config.publish, subscribe={})
        self._reserved = set(config.reserved_client_ids)
        self._key = secrets.token_bytes(32)
        self._verified: dict[str, bytes] = {}

    async def authenticate(self, *, session: Session) -> bool | None:
        user, password = session.username, session.password or ""
        if not user:
            self.context.logger.info("refused a client without username")
            return False
        self._reload_if_changed()
        digests = [d for d in [self._hashes.get(user), *self._pending.get(user, [])] if d is not None]
        if not digests or not await self._password_ok(user, password, digests):
            self.context.logger.info(f"refused {user!r}: unknown user or wrong password")
            return False
        client_id = session.client_id or ""
        if client_id in self._reserved and client_id != user:
            self.context.logger.info(f"refused {user!r}: client id {client_id!r} belongs to another id")
            return False
        if session.will_flag and not self._rules.may_publish(user, session.will_topic or ""):
            self.context.logger.info(
                f"refused {user!r}: last will on {session.will_topic!r} is not its topic"
            )
            return False
        return True

    def _reload_if_changed(self) -> None:
        """A changed file replaces the hashes (and the remembered verifications of users whose hash changed); a
        file that cannot be read keeps the last good hashes, with one line."""
        self._reload_pending()
        stamp = file_stamp(self._path)
        if stamp == self._stamp:
            return
        self._stamp = stamp
        try:
            hashes = read_password_file(self._path)
        except CredentialsError as exc:
            self.context.logger.error(f"{exc}: keeping the passwords read before")
            return
        for user in list(self._verified):
            if hashes.get(user) != self._hashes.get(user):
                del self._verified[user]
        self._hashes = hashes

    def _reload_pending(self) -> None:
        """The pending passwords, as `_reload_if_changed` reads the password file; a user whose pending ones
        changed must pass argon2 again (a withdrawn pending password must not live on in `_verified`)."""
        stamp = file_stamp(self._pending_path)
        if stamp == self._pending_stamp:
            return
        self._pending_stamp = stamp
        try:
            pending = read_pending_file(self._pending_path)
        except CredentialsError as exc:
            self.context.logger.error(f"{exc}: keeping the pending passwords read before")
            return
        for user in list(self._verified):
            if pending.get(user) != self._pending.get(user):
                del self._verified[user]
        self._pending = pending

    async def _password_ok(self, user: str, password: str, digests: list[str]) -> bool:
        tag = hmac.new(self._key, password.encode(), hashlib.sha256).digest()
        known = self._verified.get(user)
        if known is not None and hmac.compare_digest(known, tag):
            return True
        for digest in digests:
            if await asyncio.to_thread(verify_password, digest, password):
                self._verified[user] = tag
                return True
        return False
