"""Pydantic models of every MQTT payload in the wsnav contract (docs/architecture.md, "The message contract").

Payloads are small JSON objects with a version field `v`; unknown fields are refused so that a typo on a node
is noticed instead of silently ignored.
"""

from __future__ import annotations

import contextlib
import json
import struct
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from wsnav.schemas.ids import Id

CONTRACT_VERSION = 1
MAX_PAYLOAD_BYTES = 1024
"""Anything larger is dropped unread: an ESP8266 never sends more than ~120 bytes."""
MAX_OPERATOR_PAYLOAD_BYTES = 8192
"""Operator blocks and the simulated world carry polygons, so they get a larger allowance."""

ROBOT_PATH_POINTS = 24
"""A robot status carries its path ahead thinned to this many points: it stays well under MAX_PAYLOAD_BYTES."""

MAX_COUNT = 2**31 - 1
"""Every count and duration on the wire fits a signed 32-bit int, what every reader (the firmware, ROS, the
browser's JavaScript) holds without loss: a 900-digit `uptime_s` or `replans` was accepted and reached the page."""
Count = Annotated[int, Field(ge=0, le=MAX_COUNT)]

ZoneStateValue = Literal["blocked", "clear", "caution"]
NodeStatusValue = Literal["online", "offline"]
RobotStateValue = Literal["idle", "navigating", "waiting", "arrived", "cancelled"]

MAX_COORDINATE_M = 1e7
"""Points on the wire are finite and within 10,000 km of the map origin (room for maps in UTM coordinates)."""
MAX_AREA_EXTENT_M = 10_000.0
"""An operator block or simulated obstacle spans at most 10 km in x and in y (cheap to clip and rasterise)."""
Coordinate = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_COORDINATE_M, le=MAX_COORDINATE_M)]
MAX_YAW_RAD = 1e6
"""Headings may be unwrapped; any finite one this size is still an angle to sin and cos."""
Point2 = tuple[Coordinate, Coordinate]


def _check_extent(polygon: list[Point2] | None) -> None:
    if polygon:
        xs, ys = [p[0] for p in polygon], [p[1] for p in polygon]
        if max(xs) - min(xs) > MAX_AREA_EXTENT_M or max(ys) - min(ys) > MAX_AREA_EXTENT_M:
            raise ValueError(f"polygon spans more than {MAX_AREA_EXTENT_M:g} m")


Yaw = Annotated[float, Field(allow_inf_nan=False, ge=-MAX_YAW_RAD, le=MAX_YAW_RAD)]
Pose = tuple[Coordinate, Coordinate, Yaw]
"""A robot's or a goal's [x, y, yaw]: bounded like every point, so no reader's arithmetic overflows on it."""


class _Message(BaseModel):
    """Every payload of the contract: unknown fields refused, and no NaN or infinity in any number (one retained
    NaN made the console's JSON invalid, and 1.7e308 in a pose overflowed every other robot's agent)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    v: Literal[1] = CONTRACT_VERSION

    def to_payload(self) -> bytes:
        """Compact JSON bytes, as sent on the wire."""
        return self.model_dump_json(exclude_none=True).encode()


class ZoneState(_Message):
    """`zones/<zone>/state/<node>`: what one node sees in its zone; retained, QoS 1, also sent as heartbeat."""

    zone: Id
    node: Id
    state: ZoneStateValue
    seq: Count
    """Per-node, increasing; restarts from a random base on reboot are tolerated by the receiver's reset rule."""


class NodeStatus(_Message):
    """`nodes/<node>/status`: birth `online` on connect, last will `offline`; retained."""

    node: Id
    status: NodeStatusValue


ResetCause = Literal[
    "power_on",
    "watchdog",
    "exception",
    "soft_wdt",
    "soft_reset",
    "deep_sleep",
    "reset_pin",
    "unknown",
]
"""`machine.reset_cause()` on the ESP8266 is the SDK's rst_info reason 0..6, named in this order
(firmware/device/diagnostics.py maps them); anything else is `unknown`."""
MAX_HEARTBEAT_S = 3600
"""A node's heartbeat period is at most an hour (the site file's bound, and a `set_heartbeat` command's)."""
MAX_INFO_ERROR_CHARS = 32
"""A node's last error is cut to this many characters: the whole message must fit the largest free block of a
node's fragmented heap (firmware/device/diagnostics.py)."""


class NodeInfo(_Message):
    """`nodes/<node>/info`: a node's diagnostics, retained, QoS 0; after every (re)connect and every few minutes.

    `rssi` and `heap_free` are absent where there is nothing to measure (a wired or emulated node)."""

    node: Id
    fw: Annotated[str, Field(pattern=r"^[0-9A-Za-z._+-]{1,16}$")]
    """The firmware's version (firmware/device/diagnostics.py FIRMWARE_VERSION)."""
    reset: ResetCause
    """Why the board last started: a `watchdog` or `exception` after a deploy is worth a look."""
    uptime_s: Count
    rssi: Annotated[int, Field(ge=-127, le=0)] | None = None
    """Wi-Fi signal in dBm; below about -80 the link drops often."""
    heap_free: Count | None = None
    """Free GC heap in bytes after a collection."""
    reconnects: Count
    """Broker connections since boot, minus the first."""
    error: Annotated[str, Field(pattern=r'^[^"\\\x00-\x1f]*$', max_length=MAX_INFO_ERROR_CHARS)] | None = None
    """Why the broker link last went down (no quotes, backslashes or control characters), if it ever did."""
    heartbeat_ms: Annotated[int, Field(ge=0, le=MAX_HEARTBEAT_S * 1000)] | None = None
    """The heartbeat period the node runs now: its config's, or what a `set_heartbeat` command set (RAM only)."""
    bad_commands: Count | None = None
    """Commands ignored since boot: malformed, unknown, or out of range (a node that takes commands says 0)."""
    trial: Literal[True] | None = None
    """Present (true) while the node runs an over-the-air update on trial: the update is confirmed (and `trial`
    gone from the next `info`) once the node has run healthy for a while, connected, sending states."""


MAX_LOG_LINES = 8
MAX_LOG_LINE_CHARS = 60
"""A node's log ring (firmware/device/app.py, `Node.log`): its last lines, each cut to this many characters
(its uptime first): bounded bytes on the node's heap. A line may hold any character (an exception's text):
whoever shows one escapes what a terminal or a page would act on."""


class NodeLog(_Message):
    """`nodes/<node>/log`: a node's last log lines, oldest first, each `<uptime_s> <line>`; its answer to the
    operator's `log` command (`wsnav firmware logs`). QoS 0, never retained: asked for, not state."""

    node: Id
    lines: Annotated[
        list[Annotated[str, Field(max_length=MAX_LOG_LINE_CHARS)]],
        Field(max_length=MAX_LOG_LINES),
    ]


NodeCommandName = Literal["restart", "send_info", "set_heartbeat", "update", "config", "log"]
Sha256Hex = Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
MAX_COMMAND_ID = 2**30 - 1
"""Command ids stay below 2**30: a small int (no heap) on the ESP8266, as ZoneState's seq on the node."""


class NodeCommand(_Message):
    """`nodes/<node>/command`: the operator's command to one node; QoS 1, never retained (a node ignores a
    retained one, which would otherwise greet it at every connect).

    `restart`: the node publishes `offline`, disconnects and resets; `send_info`: it publishes its `info` at
    once; `set_heartbeat`: its heartbeat period becomes `heartbeat_s` until it restarts (reported in `info`);
    `update`: it reboots into update mode and fetches the OtaManifest whose HMAC-SHA256 under the node's update key
    (schemas.credentials.sign_manifest) is `manifest`, then its files
    (over-the-air update, docs/firmware-esp8266.md); `config`: the same way, it fetches a sealed configuration
    (schemas.credentials.seal_config: new Wi-Fi, broker address) whose HMAC is `manifest`, then tries it as a
    trial and goes back to its old one if it cannot get online with it; `log`: it publishes its last log lines
    (NodeLog). `id` is the sender's, random per command: the node applies a
    command once even if QoS 1 delivers it again. The whole payload stays under 128 bytes, what the node's MQTT
    client hands over (an `update` takes 120 at most)."""

    id: Annotated[int, Field(ge=1, le=MAX_COMMAND_ID)]
    command: NodeCommandName
    heartbeat_s: Annotated[float, Field(gt=0, le=MAX_HEARTBEAT_S)] | None = None
    """Only with `set_heartbeat`, bounded as the site file's heartbeat."""
    manifest: Sha256Hex | None = None
    """Only with `update` and `config`: the HMAC-SHA256 (hex) under the node's update key of the manifest's (or the
    sealed configuration's) payload, which the node checks before trusting it."""

    @model_validator(mode="after")
    def _heartbeat_with_set_heartbeat(self) -> NodeCommand:
        if (self.heartbeat_s is None) == (self.command == "set_heartbeat"):
            raise ValueError("heartbeat_s goes with set_heartbeat, and only with it")
        if (self.manifest is None) == (self.command in ("update", "config")):
            raise ValueError("manifest goes with update and config, and only with them")
        return self


OTA_CHUNK_BYTES = 512
"""File bytes per OTA chunk: a chunk (header and data) is one read and one write of the node's flash."""
OTA_MAX_FILES = 24
OTA_MAX_FILE_BYTES = 32768
OTA_MAX_MANIFEST_BYTES = 3072
"""What the node accepts: a manifest it can parse in update mode, files it can hold (the app is ~13 KB)."""
OTA_FILE_NAME = r"^[a-z][a-z0-9_]{0,23}\.mpy$"
"""Bytecode modules of the app in the board's root folder: no path, no `..`, never main.py or boot.py."""
OTA_BOOT_FILES = ("otaboot.mpy", "nodeconfig.mpy")
"""Built modules an update never replaces: main.py's boot decisions (trial boots, rollback) and safe mode rely on
them; they change only with a deploy over USB (firmware/deploy.py). nodeconfig too: main.py imports it before
otaboot can finish a swap that a power cut interrupted, so a half-moved nodeconfig.mpy (old in .bak, new in
.tmp) would stop the board at its REPL."""
OTA_CHUNK_HEADER = struct.Struct(">HII")
"""A chunk's binary header (`nodes/<node>/ota/chunk`): file index (0: the manifest, i: its i-th file), offset,
the file's whole size; then the bytes."""


class OtaFile(BaseModel):
    """One file of an update: its name on the board, its size and its sha256 (hex)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Annotated[str, Field(pattern=OTA_FILE_NAME)]
    size: Annotated[int, Field(ge=0, le=OTA_MAX_FILE_BYTES)]
    sha256: Sha256Hex


class OtaManifest(_Message):
    """File 0 of an update (`wsnav firmware ota`): the version and its files. The node fetches it first, checks
    its sha256 against the `update` command (which only the operator may send), then each file against it."""

    version: Annotated[str, Field(pattern=r"^[0-9A-Za-z._+-]{1,16}$")]
    """What `info`'s `fw` will say once the update runs (the new diagnostics.py's FIRMWARE_VERSION)."""
    files: Annotated[list[OtaFile], Field(min_length=1, max_length=OTA_MAX_FILES)]

    @model_validator(mode="after")
    def _names_once_and_not_boot(self) -> OtaManifest:
        names = [f.name for f in self.files]
        if len(set(names)) != len(names):
            raise ValueError("a file is named twice")
        if set(names) & set(OTA_BOOT_FILES):
            raise ValueError(f"{', '.join(OTA_BOOT_FILES)} change only with a deploy over USB")
        return self


class OtaRequest(_Message):
    """`nodes/<node>/ota/request`: a node in update mode asks for the chunk of file `file` (0: the manifest) at
    `offset`; the operator's tool answers on `nodes/<node>/ota/chunk`. Pulled by the node, so the transfer goes at
    the pace of the slowest of node, broker and tool."""

    file: Annotated[int, Field(ge=0, le=OTA_MAX_FILES)]
    offset: Annotated[int, Field(ge=0, le=OTA_MAX_FILE_BYTES)]


def ota_chunk(file: int, offset: int, size: int, data: bytes) -> bytes:
    """A chunk's payload: OTA_CHUNK_HEADER then `data`."""
    return OTA_CHUNK_HEADER.pack(file, offset, size) + data


def parse_ota_chunk(payload: bytes) -> tuple[int, int, int, bytes]:
    """(file, offset, size, data) of a chunk payload; PayloadError if it is too short or too long."""
    n = OTA_CHUNK_HEADER.size
    if not n <= len(payload) <= n + OTA_CHUNK_BYTES:
        raise PayloadError(f"an OTA chunk is {n} to {n + OTA_CHUNK_BYTES} bytes, not {len(payload)}")
    file, offset, size = OTA_CHUNK_HEADER.unpack_from(payload)
    return file, offset, size, payload[n:]


class RobotStatus(_Message):
    """`robots/<robot>/status`: what the agent is doing, at 2 Hz and on every state change."""

    robot: Id
    state: RobotStateValue
    pose: Pose
    goal: Id | Pose | None = None
    blocked_zones: list[Id] = Field(default_factory=list)
    replans: Count = 0
    plan_length_m: Annotated[float, Field(ge=0)] | None = None
    reason: Annotated[str, Field(max_length=200)] | None = None
    """Why the robot is `waiting` or `cancelled`, in words an operator can act on; while `navigating`, set only
    when it is driving out of a zone that became blocked around it (`leaving blocked zone z1`)."""
    path: Annotated[list[Point2], Field(max_length=ROBOT_PATH_POINTS)] | None = None
    """The global plan still ahead while navigating, thinned to at most ROBOT_PATH_POINTS points (cm), for
    operators' maps; the planner keeps the full-resolution plan."""
    t: float | None = None
    """When the status was made, on the site clock: Unix time in a real deployment (so another host can tell
    how old it is), simulated time in simulation."""
    footprint_radius: Annotated[float, Field(gt=0, le=2.0)] | None = None
    """The robot's footprint (a circle, metres), so the other robots keep clear of it; absent in older
    payloads, then the site file's radius for this robot applies."""


OPERATOR_CANCEL_REASON = "cancelled by the operator"
"""A status's `reason` when the robot stopped because an operator cancelled its goal (any other `cancelled` is the
robot giving up: the console raises an alert for those)."""


YIELD_REASON_PREFIX = "yielding to "
"""How a `waiting` status's `reason` begins while the robot gives way to a robot of the fleet with right of way
(navigation.behaviors.right_of_way): a wait on purpose, which the console must not take for a stuck robot."""


def is_yielding(state: str | None, reason: str | None) -> bool:
    """Whether a robot status (its state and reason) says the robot waits only to give another robot way."""
    return state == "waiting" and reason is not None and reason.startswith(YIELD_REASON_PREFIX)


class RobotGoal(_Message):
    """`robots/<robot>/goal`: a named point of the site or an [x, y, yaw] pose; `cancel` stops the robot."""

    goal: Id | Pose | None = None
    cancel: bool = False

    @model_validator(mode="after")
    def _goal_or_cancel(self) -> RobotGoal:
        if (self.goal is None) == (not self.cancel):
            raise ValueError("give exactly one of 'goal' or 'cancel': true")
        return self


class OperatorBlock(_Message):
    """`operator/blocks/<id>`: a temporary keep-out area set by an operator; retained, empty payload removes it."""

    zone: Id | None = None
    polygon: Annotated[list[Point2], Field(min_length=3, max_length=64)] | None = None
    expires_at: float | None = None
    """When the block stops applying, on the site clock: Unix time in a real deployment (written on one host,
    read on another), simulated time in simulation; None: until removed."""
    reason: Annotated[str, Field(max_length=200)] | None = None

    @model_validator(mode="after")
    def _zone_or_polygon(self) -> OperatorBlock:
        if (self.zone is None) == (self.polygon is None):
            raise ValueError("give exactly one of 'zone' or 'polygon'")
        _check_extent(self.polygon)
        return self


class SimObstacle(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    id: Id
    zone: Id | None = None
    """The zone the scenario placed it in, if any (the paper's obstacles fill a zone)."""
    polygon: Annotated[list[Point2], Field(min_length=3, max_length=64)]

    @model_validator(mode="after")
    def _bounded(self) -> SimObstacle:
        _check_extent(self.polygon)
        return self


class SimWorld(_Message):
    """`sim/world`: simulation only, retained: the obstacles the zone simulator placed, for simulated lidars.

    The whole set every time, so a late subscriber needs only the retained copy.
    """

    t: float
    """Simulated time of the change."""
    obstacles: Annotated[list[SimObstacle], Field(max_length=256)] = Field(default_factory=list)


M = TypeVar("M", bound=_Message)

MESSAGE_MODELS: dict[str, type[_Message]] = {
    "zone_state": ZoneState,
    "node_status": NodeStatus,
    "node_info": NodeInfo,
    "node_command": NodeCommand,
    "node_log": NodeLog,
    "ota_manifest": OtaManifest,
    "ota_request": OtaRequest,
    "robot_status": RobotStatus,
    "robot_goal": RobotGoal,
    "operator_block": OperatorBlock,
    "sim_world": SimWorld,
}


class PayloadError(ValueError):
    """A payload that must be dropped: the message says why, in one line."""


class NotJson(PayloadError):
    """Text that is not JSON at all (as opposed to JSON the contract refuses)."""


def refuse_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """`{"state": "clear", "state": "blocked"}` means two things; JSON parsers keep the last, so refuse it."""
    keys = [key for key, _ in pairs]
    if len(set(keys)) != len(keys):
        duplicate = next(key for key in keys if keys.count(key) > 1)
        raise PayloadError(f"duplicate key {duplicate!r}")
    return dict(pairs)


def parse_json(raw: bytes | str) -> Any:
    """JSON text as the contract reads it: one key twice or nesting Python cannot parse is a PayloadError, as is
    text that is not JSON; nothing else is raised."""
    try:
        return json.loads(raw, object_pairs_hook=refuse_duplicate_keys)
    except PayloadError:
        raise
    except (ValueError, UnicodeDecodeError):  # JSONDecodeError, and ints over Python's digit limit
        raise NotJson("not valid JSON") from None
    except RecursionError:  # `[` x 4000: Python's parser gives up on depth, a reader must not
        raise PayloadError("JSON nested too deeply") from None


def parse_payload(model: type[M], payload: bytes | str, *, max_bytes: int = MAX_PAYLOAD_BYTES) -> M:
    """Validate raw bytes against a model; raises PayloadError with a one-line reason, never anything else."""
    raw = payload.encode() if isinstance(payload, str) else payload
    if len(raw) > max_bytes:
        raise PayloadError(f"payload of {len(raw)} bytes exceeds {max_bytes}")
    with contextlib.suppress(NotJson):  # pydantic below says where
        parse_json(raw)
    try:
        return model.model_validate_json(raw)
    except ValidationError as exc:
        first: dict[str, Any] = dict(exc.errors()[0])
        where = ".".join(str(p) for p in first.get("loc", ())) or "payload"
        raise PayloadError(f"{model.__name__}: {where}: {first.get('msg', 'invalid')}") from None
