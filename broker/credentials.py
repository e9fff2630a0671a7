"""The credentials folder: one `<id>.json` per node, robot and the operator, plus the broker's password file
and the site's update key (`update.key`: each node's config holds the key derived from it for its id).

Secrets are generated once and then kept: a rerun reuses every existing password (so deployed nodes keep
working), gives new ids new passwords, refreshes the site-derived fields of node configs (zone, sensor,
heartbeat, debounce), and reports files whose id left the site instead of deleting them. Everything is written
owner-only (files 0600, folder 0700) because these files are the keys to the site.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError
from pydantic import ValidationError

from wsnav.schemas.credentials import (
    UPDATE_KEY_FILE,
    BrokerAddress,
    Credentials,
    CredentialsError,
    NodeConfig,
    WifiConfig,
    load_credentials,
    node_update_key,
    operator_logins,
    read_json_object,
)
from wsnav.schemas.site_file import SiteFile

PASSWORD_FILE = "broker.passwd"
"""`username:<argon2 hash>` lines; the format amqtt's FileAuthPlugin also reads."""
PENDING_FILE = "broker.pending"
"""The same lines, for passwords a node is changing to (`wsnav firmware config --new-password`): the amqtt broker
takes them beside the password file's, so the node is never locked out, until it confirms one (`promote_pending`)."""
OPERATOR = "operator"
DASHBOARD = "dashboard"
"""A read-only identity for dashboards (Home Assistant): it reads the site and publishes nothing of it."""

# The passwords are 192-bit random tokens, so a slow hash adds no real protection against guessing; modest
# argon2id parameters keep a connect at a few ms on a Raspberry Pi even when 1000 nodes join at once.
HASHER = PasswordHasher(time_cost=1, memory_cost=8192, parallelism=1)


@dataclass
class CredentialsReport:
    """What a `write_credentials` run did, for the one-line-per-id summary."""

    created: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)
    renewed: list[str] = field(default_factory=list)
    stale: list[str] = field(default_factory=list)
    """Files `<id>.json` whose id is no longer in the site (left in place, not in the password file)."""


def new_password() -> str:
    """32 URL-safe characters: no ':' (password file separator) and easy to type into a device console."""
    return secrets.token_urlsafe(24)


def site_ids(spec: SiteFile) -> list[str]:
    """Every username of the site: nodes, robots, the operator and the dashboard."""
    ids = [n.id for n in spec.nodes] + [r.id for r in spec.robots]
    for reserved in (OPERATOR, DASHBOARD):
        if reserved in ids:
            raise CredentialsError(
                f"site {spec.name}: the id {reserved!r} is reserved for the {reserved}'s credentials"
            )
    return [*ids, OPERATOR, DASHBOARD]


def write_credentials(
    spec: SiteFile,
    out: Path,
    broker: tuple[str, int] | None = None,
    wifi_ssid: str | None = None,
    wifi_password: str | None = None,
    renew: frozenset[str] = frozenset(),
) -> CredentialsReport:
    """Create or refresh the credentials folder `out` for the site; see the module docstring for the rules.

    `broker` and the Wi-Fi settings, when given, replace what existing files hold; otherwise those are kept.
    The ids in `renew` get new passwords (revocation: the old ones stop working).
    """
    secure_dir(out)
    site_key = _site_update_key(out / UPDATE_KEY_FILE)
    existing = {p.stem: p for p in out.glob("*.json")}
    report = CredentialsReport()
    passwords: dict[str, str] = {}
    node_by_id = {n.id: n for n in spec.nodes}
    robot_ids = {r.id for r in spec.robots}
    for ident in site_ids(spec):
        old = read_json_object(existing[ident]) if ident in existing else None
        kept = None if ident in renew else _password_of(old, existing.get(ident))
        password = kept or new_password()
        address = _broker_of(old, broker)
        wifi = _wifi_of(old, wifi_ssid, wifi_password)
        record: Credentials
        if ident in node_by_id:
            node = node_by_id[ident]
            keepalive = old.get("keepalive_s") if old else None
            keepalive_s = keepalive if isinstance(keepalive, int) and 5 <= keepalive <= 3600 else 30
            record = NodeConfig(
                role="node",
                username=ident,
                password=password,
                site=spec.name,
                broker=address,
                node=ident,
                zone=node.zone,
                sensor=node.sensor,
                heartbeat_s=spec.heartbeat_of(node),
                on_delay_ms=node.on_delay_ms,
                off_delay_ms=node.off_delay_ms,
                keepalive_s=keepalive_s,
                wifi=wifi,
                update_key=node_update_key(site_key, ident),
            )
        else:
            role = "robot" if ident in robot_ids else "dashboard" if ident == DASHBOARD else "operator"
            record = Credentials(username=ident, password=password, role=role, site=spec.name, broker=address)
        write_private(out / f"{ident}.json", record.model_dump_json(indent=2) + "\n")
        passwords[ident] = password
        (report.renewed if ident in renew else report.kept if old else report.created).append(ident)
    report.stale = sorted(name for name in existing if name not in passwords)
    write_password_file(out / PASSWORD_FILE, with_tool_logins(passwords))
    return report


def _site_update_key(path: Path) -> str:
    """The site's update key (schemas.credentials.UPDATE_KEY_FILE), made once and kept: every node's key derives
    from it, so a new one would lock deployed nodes out of updates over the air until redeployed by USB."""
    if path.exists():
        try:
            key = path.read_text().strip()
        except OSError as exc:
            raise CredentialsError(f"{path}: cannot read: {exc.strerror}") from None
        if len(key) != 64 or any(c not in "0123456789abcdef" for c in key):
            raise CredentialsError(f"{path}: not an update key (64 hex digits); restore it from a backup")
        return key
    key = secrets.token_hex(32)
    write_private(path, key + "\n")
    return key


def with_tool_logins(passwords: dict[str, str]) -> dict[str, str]:
    """username -> password for the broker: the operator's password also under each of its tools' names."""
    out = dict(passwords)
    if OPERATOR in passwords:
        out.update(dict.fromkeys(operator_logins(OPERATOR), passwords[OPERATOR]))
    return out


def write_password_file(path: Path, passwords: dict[str, str]) -> None:
    """The argon2 password file; an existing line is kept when it still matches, so reruns cause no churn."""
    old = read_password_file(path) if path.exists() else {}
    lines = []
    checked: dict[tuple[str, str], bool] = {}  # the operator's tools' 64 logins share one password and hash
    made: dict[str, str] = {}
    for user, password in passwords.items():
        digest = old.get(user)
        if digest is not None and (digest, password) not in checked:
            checked[digest, password] = verify_password(digest, password)
        if digest is None or not checked[digest, password]:
            digest = made.get(password) or HASHER.hash(password)
        made.setdefault(password, digest)
        lines.append(f"{user}:{digest}\n")
    write_private(path, "".join(lines))


def read_password_file(path: Path) -> dict[str, str]:
    """username -> argon2 hash; raises CredentialsError naming the file and line on anything malformed."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise CredentialsError(
            f"{path}: no password file (run `wsnav broker credentials --site SITE --out {path.parent}`)"
        ) from None
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot read: {exc.strerror}") from None
    return dict(_hash_lines(path, text))


def _hash_lines(path: Path, text: str) -> list[tuple[str, str]]:
    """The `username:$argon2...` lines of a password or pending file, in order."""
    lines: list[tuple[str, str]] = []
    for number, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        user, sep, digest = line.partition(":")
        if not sep or not user or not digest.startswith("$argon2"):
            raise CredentialsError(f"{path}: line {number}: expected `username:$argon2...`")
        lines.append((user, digest))
    return lines


def read_pending_file(path: Path) -> dict[str, list[str]]:
    """username -> the argon2 hashes of its pending passwords (PENDING_FILE); none when the file is missing."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot read: {exc.strerror}") from None
    pending: dict[str, list[str]] = {}
    for user, digest in _hash_lines(path, text):
        pending.setdefault(user, []).append(digest)
    return pending


def add_pending(folder: Path, user: str, password: str) -> None:
    """`password` accepted for `user` beside its own from now on (the amqtt broker reads PENDING_FILE again when
    it changes), until `promote_pending`. Earlier pending passwords of `user` stay: a change that was never
    confirmed may still have reached the node."""
    path = folder / PENDING_FILE
    lines = [(u, d) for u, ds in read_pending_file(path).items() for d in ds]
    lines.append((user, HASHER.hash(password)))
    write_private(path, "".join(f"{u}:{d}\n" for u, d in lines))


def promote_pending(folder: Path, user: str, password: str) -> None:
    """The node confirmed `password` (a pending one): it becomes `user`'s in `<user>.json` and in the password
    file (the pending line's very hash, which tells the broker's watch a promotion from a revocation), then its
    pending lines go, the old password with them. In this order, a crash at any step leaves the node a password
    the broker takes."""
    pending_path = folder / PENDING_FILE
    pending = read_pending_file(pending_path)
    digest = next((d for d in pending.get(user, []) if verify_password(d, password)), None)
    if digest is None:
        raise CredentialsError(f"{pending_path}: no pending password of {user!r} matches")
    path = folder / f"{user}.json"
    creds = load_credentials(path)
    write_private(path, creds.model_copy(update={"password": password}).model_dump_json(indent=2) + "\n")
    passwd = folder / PASSWORD_FILE
    hashes = read_password_file(passwd)
    hashes[user] = digest
    write_private(passwd, "".join(f"{u}:{d}\n" for u, d in hashes.items()))
    pending.pop(user)
    write_private(pending_path, "".join(f"{u}:{d}\n" for u, ds in pending.items() for d in ds))


def withdraw_pending(folder: Path, user: str, password: str | None = None) -> None:
    """`password` no longer pending for `user` (a change that did not happen: the node went back to its old
    password; an earlier change that was never confirmed keeps its line, the node may have taken it), or, without
    `password`, none of `user`'s (a revoked identity, `wsnav broker revoke`)."""
    path = folder / PENDING_FILE
    pending = read_pending_file(path)
    digests = pending.pop(user, [])
    kept = [d for d in digests if password is not None and not verify_password(d, password)]
    if kept:
        pending[user] = kept
    if len(kept) != len(digests):
        write_private(path, "".join(f"{u}:{d}\n" for u, ds in pending.items() for d in ds))


def file_stamp(path: Path) -> tuple[int, int, int] | None:
    """What changes when a file is rewritten (write_private replaces it: a new inode); None if it is missing."""
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def verify_password(digest: str, password: str) -> bool:
    try:
        return HASHER.verify(digest, password)
    except (VerifyMismatchError, VerificationError, InvalidHashError):
        return False


def load_folder(folder: Path, spec: SiteFile) -> dict[str, Credentials]:
    """Every site id's credentials from the folder; a missing or broken file is an error naming it."""
    if not folder.is_dir():
        raise CredentialsError(f"{folder}: not a credentials folder (run `wsnav broker credentials`)")
    found: dict[str, Credentials] = {}
    for ident in site_ids(spec):
        path = folder / f"{ident}.json"
        if not path.exists():
            raise CredentialsError(f"{path}: missing (rerun `wsnav broker credentials` for this site)")
        creds = load_credentials(path)
        if creds.username != ident:
            raise CredentialsError(f"{path}: username {creds.username!r} does not match the file name")
        found[ident] = creds
    return found


def _password_of(old: dict[str, object] | None, path: Path | None) -> str | None:
    if old is None:
        return None
    password = old.get("password")
    if not isinstance(password, str) or len(password) < 16:
        raise CredentialsError(
            f"{path}: password: missing or shorter than 16 characters; fix or remove the file"
        )
    return password


def _broker_of(old: dict[str, object] | None, given: tuple[str, int] | None) -> BrokerAddress:
    if given is not None:
        return BrokerAddress(host=given[0], port=given[1])
    if old and isinstance(old.get("broker"), dict):
        try:
            return BrokerAddress.model_validate(old["broker"])
        except ValidationError:
            pass
    return BrokerAddress()


def _wifi_of(old: dict[str, object] | None, ssid: str | None, password: str | None) -> WifiConfig:
    wifi = WifiConfig()
    if old and isinstance(old.get("wifi"), dict):
        with contextlib.suppress(ValidationError):
            wifi = WifiConfig.model_validate(old["wifi"])
    if ssid is not None:
        wifi = wifi.model_copy(update={"ssid": ssid})
    if password is not None:
        wifi = wifi.model_copy(update={"password": password})
    return wifi


def secure_dir(path: Path) -> None:
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(path, 0o700)
    except OSError as exc:
        raise CredentialsError(f"{path}: cannot create the credentials folder: {exc.strerror}") from None


def write_private(path: Path, text: str) -> None:
    """Atomic, owner-only write: a crash never leaves a half-written key file, and no one else can read it."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise CredentialsError(f"{path}: cannot write: {exc.strerror}") from None
