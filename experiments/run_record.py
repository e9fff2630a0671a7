"""One run kept whole, as an MCAP file that Foxglove (or the `mcap` CLI) opens: the robot's true pose at every
step, each plan the navigator makes, every message the agent takes in with its simulated time of arrival, the
navigator's state changes and its events (plans, recoveries, aborts), and the run's row. Written only on request
(`wsnav experiment --record DIR`): 0.3 MB for a 217 s `full` run, 0.64 MB for a 423 s `default` run and
its 2115 plans (zstd-compressed chunks).

Log times are simulated nanoseconds since the run's world started (the clock the run keeps); channels carry
JSON with a JSON schema each, the robot's pose as Foxglove's `foxglove.PoseInFrame` so its 3D panel draws it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Reversible, Sequence
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wsnav.experiments.run_plan import RunSpec
from wsnav.navigation.navigator import NavEvent
from wsnav.runtime.bus import Message

if TYPE_CHECKING:
    from mcap.writer import Writer

FRAME = "map"
_NUMBER = {"type": "number"}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_XYZ = {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER}}
_QUAT = {"type": "object", "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER}}
SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.PoseInFrame": {
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": {"type": "object", "properties": {"position": _XYZ, "orientation": _QUAT}},
        },
    },
    "wsnav.Plan": {
        "type": "object",
        "description": "The navigator's path as planned: (x, y) in metres, map frame, rounded to 1 mm.",
        "properties": {"points": {"type": "integer"}, "xy": {"type": "array", "items": _NUMBER}},
    },
    "wsnav.Message": {
        "type": "object",
        "description": "An MQTT message as the agent took it in; payload as text.",
        "properties": {
            "topic": {"type": "string"},
            "payload": {"type": "string"},
            "retain": {"type": "boolean"},
            "received_at": _NUMBER,
        },
    },
    "wsnav.NavState": {"type": "object", "properties": {"state": {"type": "string"}}},
    "wsnav.NavEvent": {
        "type": "object",
        "properties": {
            "kind": {"type": "string"},
            "trigger": {"type": ["string", "null"]},
            "detail": {"type": ["string", "null"]},
        },
    },
}
CHANNELS = {
    "/robot/pose": "foxglove.PoseInFrame",
    "/navigator/plan": "wsnav.Plan",
    "/agent/messages": "wsnav.Message",
    "/navigator/state": "wsnav.NavState",
    "/navigator/events": "wsnav.NavEvent",
}


class RecordError(Exception):
    """The record cannot be written (the `mcap` package missing, or the folder not writable); one line."""


def record_name(config: str, route: str, run: int) -> str:
    """`default_A-B_run07`: one file name per run (its record, its picture), sortable, without characters
    shells mind."""
    return f"{config}_{route.replace('->', '-')}_run{run:02d}"


def _ns(t: float) -> int:
    return max(0, round(t * 1e9))


def require_mcap() -> None:
    """Raise RecordError (one line) when the mcap package is not installed."""
    try:
        import mcap.writer  # noqa: F401  # the optional `experiment` extra: only recording needs it
    except ImportError:
        raise RecordError(
            "recording needs the mcap package: pip install -c constraints.txt 'wsnav[research]'"
        ) from None


class RunRecorder:
    """Writes one run's record as it happens; close() (or the with-block) finishes the file."""

    def __init__(self, path: Path, spec: RunSpec) -> None:
        require_mcap()
        from mcap.writer import Writer

        try:
            self._file = path.open("wb")
        except OSError as exc:
            raise RecordError(f"{path}: cannot write: {exc.strerror}") from None
        self._writer: Writer = Writer(self._file)
        self._writer.start(profile="", library="wsnav")
        schema_ids = {
            name: self._writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
            for name, schema in SCHEMAS.items()
        }
        self._channels = {
            topic: self._writer.register_channel(topic, "json", schema_ids[schema])
            for topic, schema in CHANNELS.items()
        }
        self._writer.add_metadata(
            "run",
            {
                "config": spec.config,
                "route": spec.route,
                "blocked": spec.blocked_label,
                "run": str(spec.run),
                "seed": str(spec.seed),
            },
        )
        self._state: str | None = None
        self._plan: NDArray[np.float64] | None = None
        self._last_event: NavEvent | None = None

    def _add(self, topic: str, t: float, message: Mapping[str, object]) -> None:
        ns = _ns(t)
        self._writer.add_message(self._channels[topic], ns, json.dumps(message).encode(), ns)

    def pose(self, t: float, x: float, y: float, yaw: float) -> None:
        ns = _ns(t)
        self._add(
            "/robot/pose",
            t,
            {
                "timestamp": {"sec": ns // 10**9, "nsec": ns % 10**9},
                "frame_id": FRAME,
                "pose": {
                    "position": {"x": x, "y": y, "z": 0.0},
                    "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
                },
            },
        )

    def navigator(
        self, t: float, state: str, path: NDArray[np.float64], events: Reversible[NavEvent]
    ) -> None:
        """What changed in the navigator since the last call: its state, its plan (recorded when it is a new
        array: the navigator replaces, never edits, its path), its new events."""
        if state != self._state:
            self._state = state
            self._add("/navigator/state", t, {"state": state})
        if path is not self._plan:
            self._plan = path
            xy = np.round(np.asarray(path, dtype=np.float64).reshape(-1), 3)
            self._add("/navigator/plan", t, {"points": len(path), "xy": xy.tolist()})
        new: list[NavEvent] = []
        for event in reversed(events):  # a bounded deque: find where the last call left off, from the end
            if event is self._last_event:
                break
            new.append(event)
        for event in reversed(new):
            self._add(
                "/navigator/events",
                event.t,
                {"kind": event.kind, "trigger": event.trigger, "detail": event.detail},
            )
        if new:
            self._last_event = new[0]

    def messages(self, got: Sequence[Message]) -> None:
        for m in got:
            self._add(
                "/agent/messages",
                m.received_at,
                {
                    "topic": m.topic,
                    "payload": m.payload.decode("utf-8", "replace"),
                    "retain": m.retain,
                    "received_at": m.received_at,
                },
            )

    def result(self, row: Mapping[str, object]) -> None:
        self._writer.add_metadata("result", {k: str(v) for k, v in row.items()})

    def close(self) -> None:
        self._writer.finish()
        self._file.close()

    def __enter__(self) -> RunRecorder:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
