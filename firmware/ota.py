"""`wsnav firmware ota`: over-the-air app updates, the operator's side (the node's: device/updater.py).

The update is the build's `.mpy` modules (never main.py, boot.py, otaboot.mpy or nodeconfig.mpy: schemas
OTA_BOOT_FILES) and a manifest naming them with their sizes and sha256 (schemas.messages.OtaManifest). Each node gets an `update`
command carrying the manifest's HMAC-SHA256 under that node's update key (`Update.signature`), reboots into
update mode and pulls the manifest and the files chunk by chunk (`nodes/<node>/ota/request` ->
`nodes/<node>/ota/chunk`): `OtaServer` answers every request, whichever
node and whenever it comes (a node that lost power mid-transfer starts again), and follows each node until its
`info` says the new version confirmed (done: the node ran it healthy for a while, health.apply; an `info`
with `trial` is only a start) or says why not (failed: an error, or the old version back after a rollback).
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from pydantic import ValidationError

from wsnav.firmware.build import DEVICE, build
from wsnav.runtime.bus import Message
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas import topics
from wsnav.schemas.credentials import sign_manifest
from wsnav.schemas.messages import (
    OTA_BOOT_FILES,
    OTA_CHUNK_BYTES,
    NodeInfo,
    OtaFile,
    OtaManifest,
    OtaRequest,
    PayloadError,
    ota_chunk,
    parse_payload,
)

_VERSION = re.compile(r'^FIRMWARE_VERSION = "([^"]+)"$', re.MULTILINE)


FAT_REFUSED = "ota: FAT filesystem"
"""What a node's `info` says when its updater found FAT (device/fscheck.py)."""
FAT_ADVICE = (
    "its flash is FAT, where a power cut mid-update can leave it unreadable: back up config.json, "
    "`wsnav firmware flash` (erases; MicroPython 1.13+ makes littlefs), then `wsnav firmware deploy` over USB"
)
"""Also deploy's (firmware/deploy.py), which refuses FAT for the same reason."""


class OtaError(Exception):
    """The update cannot be made (build, version, sizes): one line for the user."""


@dataclass(frozen=True)
class Update:
    """What the nodes fetch: index 0 is the manifest's payload, index i its i-th file."""

    manifest: OtaManifest
    payloads: list[bytes]

    @property
    def digest(self) -> str:
        import hashlib

        return hashlib.sha256(self.payloads[0]).hexdigest()

    def signature(self, node_key: str) -> str:
        """The `update` command's `manifest` for the node whose update key is `node_key`: the manifest signed
        (schemas.credentials.sign_manifest), which its updater checks before it takes any file."""
        return sign_manifest(node_key, self.payloads[0])

    @property
    def total(self) -> int:
        return sum(len(p) for p in self.payloads)


def firmware_version(source: Path = DEVICE) -> str:
    """diagnostics.py's FIRMWARE_VERSION: what a node's `info` says once the update runs."""
    try:
        match = _VERSION.search((source / "diagnostics.py").read_text())
    except OSError as exc:
        raise OtaError(f"{source / 'diagnostics.py'}: {exc.strerror}") from None
    if match is None:
        raise OtaError(f"{source / 'diagnostics.py'}: no FIRMWARE_VERSION line")
    return match.group(1)


def make_update(build_dir: Path, source: Path = DEVICE) -> Update:
    """Build `source` into `build_dir` (firmware.build) and make the update of its modules."""
    import hashlib

    version = firmware_version(source)
    missing = [n for n in ("main.py", "boot.py", "app.py") if not (source / n).is_file()]
    if missing:
        raise OtaError(f"{source}: not the firmware's sources (no {', '.join(missing)})")
    build(build_dir, source)
    paths = sorted(p for p in build_dir.glob("*.mpy") if p.name not in OTA_BOOT_FILES)
    datas = [p.read_bytes() for p in paths]
    try:
        manifest = OtaManifest(
            version=version,
            files=[
                OtaFile(name=p.name, size=len(d), sha256=hashlib.sha256(d).hexdigest())
                for p, d in zip(paths, datas, strict=True)
            ],
        )
    except ValidationError as exc:
        first = exc.errors()[0]
        raise OtaError(
            f"cannot make the update: {'.'.join(map(str, first['loc']))}: {first['msg']}"
        ) from None
    return Update(manifest, [manifest.to_payload(), *datas])


@dataclass
class NodeProgress:
    """One node's transfer as the server sees it."""

    node: str
    started: bool = False
    """It asked for a chunk: an `info` from now on tells how the update went."""
    trial: bool = False
    """Its new version runs on trial: not done until an `info` without `trial` (the node's health confirmed it)."""
    done: bool = False
    error: str | None = None
    served: int = 0
    """The furthest byte of the update it has asked for (the manifest and every file, in order)."""
    shown: int = -1
    """The last progress step (tenths) printed."""
    chunks: int = 0
    first_at: float | None = None
    last_at: float | None = None
    """time.monotonic() of its first request and of the chunk that completed the update's last byte."""


class NodeTransfer:
    """Serves what `nodes` fetch over an operator's connection (`payloads`, chunk by chunk on their
    `ota/request`) and follows each to its end in their `info` (`_info`): an update (OtaServer) or a
    configuration (firmware/ota_config.py)."""

    what = "update"

    def __init__(self, bus: MqttBus, site: str, nodes: list[str], say: Callable[[str], None] = print) -> None:
        self.bus = bus
        self.site = site
        self.nodes = nodes
        self.say = say
        self.progress = {n: NodeProgress(n) for n in nodes}
        self.followers: list[MqttBus] = []
        """Other brokers' connections where the nodes may come back (a configuration moving them there)."""

    def follow_on(self, bus: MqttBus) -> None:
        """Also follow the nodes' `info` on `bus`: a node sent to another broker confirms there, not here."""
        for n in self.nodes:
            bus.subscribe(topics.node_info(self.site, n), qos=0)
        self.followers.append(bus)

    def payloads(self, node: str) -> list[bytes]:
        """What `node` fetches: index 0 first (a manifest, a sealed configuration), then any files."""
        raise NotImplementedError

    def _info(self, prog: NodeProgress, payload: bytes) -> None:
        """One `info` of a node that asked for something: done, failed, or on its way."""
        raise NotImplementedError

    def subscribe(self) -> None:
        for n in self.nodes:
            self.bus.subscribe(topics.node_ota_request(self.site, n), qos=0)
            self.bus.subscribe(topics.node_info(self.site, n), qos=0)

    def pending(self) -> list[NodeProgress]:
        return [p for p in self.progress.values() if not p.done and p.error is None]

    def handle(self, msg: Message, *, infos_only: bool = False) -> None:
        """One message from a node: a request is answered, an info may end its update."""
        parsed = topics.parse(msg.topic)
        if parsed is None or parsed.node not in self.progress:
            return
        prog = self.progress[parsed.node]
        if parsed.kind == "node_ota_request" and not infos_only:
            self._serve(prog, msg.payload)
        elif parsed.kind == "node_info" and not msg.retain and not prog.done:
            self._info(prog, msg.payload)

    def _serve(self, prog: NodeProgress, payload: bytes) -> None:
        try:
            req = parse_payload(OtaRequest, payload)
        except PayloadError as exc:
            self.say(f"{prog.node}: bad request ignored: {exc}")
            return
        payloads = self.payloads(prog.node)
        if req.file >= len(payloads):
            self.say(f"{prog.node}: asked for file {req.file}, the update has {len(payloads) - 1}")
            return
        data = payloads[req.file]
        part = data[req.offset : req.offset + OTA_CHUNK_BYTES]
        self.bus.publish(
            topics.node_ota_chunk(self.site, prog.node),
            ota_chunk(req.file, req.offset, len(data), part),
            qos=1,
        )
        prog.started = True
        prog.error = None
        now = time.monotonic()
        if prog.first_at is None:
            prog.first_at = now
        prog.chunks += 1
        total = sum(len(p) for p in payloads)
        prog.served = sum(len(p) for p in payloads[: req.file]) + req.offset + len(part)
        if prog.served == total:
            prog.last_at = now
        step = prog.served * 10 // total
        if step != prog.shown:
            prog.shown = step
            self.say(f"{prog.node}: {prog.served}/{total} B ({prog.served * 100 // total}%)")

    def run(self, timeout_s: float) -> list[str]:
        """Serve until every node is done or failed, or `timeout_s`; the failures, one line each."""
        deadline = time.monotonic() + timeout_s
        while self.pending() and time.monotonic() < deadline:
            if self.bus.wait(min(0.25 if self.followers else 0.5, max(0.0, deadline - time.monotonic()))):
                for msg in self.bus.poll():
                    self.handle(msg)
            for follower in self.followers:
                for msg in follower.poll():
                    self.handle(msg, infos_only=True)  # chunks are served where they were asked for
        failures = [p.error for p in self.progress.values() if p.error is not None]
        for p in self.pending():
            where = (
                "running it on trial, never confirmed"
                if p.trial
                else f"stopped at {p.served}/{sum(len(x) for x in self.payloads(p.node))} B"
                if p.started
                else f"never asked for the {self.what}"
            )
            failures.append(f"{p.node}: not confirmed within {timeout_s:g} s ({where})")
        return failures


class OtaServer(NodeTransfer):
    """Serves one update to `nodes` over an operator's connection and follows each to its end."""

    def __init__(
        self, bus: MqttBus, site: str, update: Update, nodes: list[str], say: Callable[[str], None] = print
    ) -> None:
        super().__init__(bus, site, nodes, say)
        self.update = update

    def payloads(self, node: str) -> list[bytes]:
        del node  # the same update for every node
        return self.update.payloads

    def _info(self, prog: NodeProgress, payload: bytes) -> None:
        try:
            info = parse_payload(NodeInfo, payload)
        except PayloadError:
            return
        version = self.update.manifest.version
        refused = info.error is not None and info.error.startswith("ota:")
        if not prog.started and not refused:
            return  # its infos before it asked for anything say nothing of this update
        if info.error is not None and info.error.startswith(("ota:", "safe:")):
            prog.error = f"{prog.node}: update failed: {info.error}"
            if info.error == FAT_REFUSED:
                prog.error += f" ({FAT_ADVICE})"
        elif info.fw == version and info.trial:
            if not prog.trial:
                prog.trial = True
                self.say(f"{prog.node}: running {version} on trial, waiting for it to confirm")
        elif info.fw == version:
            prog.done = True
            self.say(f"{prog.node}: running {version}, confirmed")
        else:
            prog.error = f"{prog.node}: came back on {info.fw}, not {version} (the update was abandoned or rolled back)"
        if prog.error is not None:
            self.say(prog.error)
