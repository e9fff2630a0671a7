"""The zone rule: what the nodes say about their zones, turned into one costmap cost per zone (the costmap's
zone layer, navigation.costmap.layers.ZoneCostLayer, paints what this decides).

Pure state (no MQTT, no threads, no clock of its own): the intake feeds it validated messages with the time they
arrived, the costmap asks it which areas changed and paints their costs. Rules: `blocked` -> lethal, `caution` -> `policy.caution_cost`; a node silent for
`policy.stale_after_heartbeats` heartbeat periods, or `offline`, is stale and read by `policy.stale` (keep its
last word, unknown, or lethal): freshness is judged by message age because amqtt never drops a silent client.
Several nodes on one zone are fused by `policy.fuse`; operator blocks (a zone or a polygon) are lethal until
they expire or are removed.
"""

from __future__ import annotations

import heapq
from collections.abc import Collection
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wsnav.schemas.messages import NodeStatus, OperatorBlock, ZoneState
from wsnav.schemas.site_file import SiteFile, ZonePolicy
from wsnav.zones.cost_values import FREE_SPACE, LETHAL_OBSTACLE, NO_INFORMATION
from wsnav.zones.geometry import Bounds, CellWindow, GridFrame, polygon_window

Word = Literal["clear", "caution", "unknown", "blocked"]
"""What one node says about its zone once staleness is applied; ordered by precedence."""
_RANK: dict[Word, int] = {"clear": 0, "caution": 1, "unknown": 2, "blocked": 3}

AreaKey = tuple[Literal["zone", "block"], str]


@dataclass(frozen=True, order=True)
class BlockedArea:
    """A lethal area a robot may stand in and must be let out of: a blocked zone or an operator polygon block."""

    kind: Literal["zone", "block"]
    id: str

    @property
    def name(self) -> str:
        """How reasons and logs name it: the zone's id, or `operator/<id>` for a polygon block."""
        return self.id if self.kind == "zone" else f"operator/{self.id}"


@dataclass
class _NodeView:
    """What the layer knows of one node: its last zone state and when any message last came from it."""

    zone: str
    heartbeat_s: float
    state: str | None = None
    heard_at: float | None = None
    online: bool = True


@dataclass(frozen=True)
class _Block:
    zone: str | None
    window: CellWindow | None
    expires_at: float | None


class ZoneRule:
    """Effective cost per zone (and per operator polygon) from node messages, fused and aged by the policy."""

    def __init__(self, spec: SiteFile, frame: GridFrame, policy: ZonePolicy | None = None) -> None:
        self.spec = spec
        self.frame = frame
        self.policy = policy if policy is not None else spec.policy
        self._zone_ids = [z.id for z in spec.zones]
        self._windows: dict[str, CellWindow] = {z.id: polygon_window(z.polygon, frame) for z in spec.zones}
        self._nodes: dict[str, _NodeView] = {
            n.id: _NodeView(n.zone, spec.heartbeat_of(n)) for n in spec.nodes
        }
        self._watchers: dict[str, list[str]] = {z: [] for z in self._zone_ids}
        for n in spec.nodes:
            self._watchers[n.zone].append(n.id)
        self._blocks: dict[str, _Block] = {}
        self._now: float | None = None
        self._started: float | None = None
        self._costs: dict[str, int] = dict.fromkeys(self._zone_ids, FREE_SPACE)
        self._polys: dict[str, CellWindow] = {}
        self._pending: dict[AreaKey, Bounds] = {}
        self._due: dict[str, float] = {}
        """Per node: the time after which it turns stale if nothing is heard (its zone is looked at then)."""
        self._deadlines: list[tuple[float, str]] = []
        """A heap of (deadline, node); an entry no longer in `_due` is outdated and skipped."""

    # -- inputs ---------------------------------------------------------------------------------------------

    def on_zone_state(self, msg: ZoneState, received_at: float) -> bool:
        """A validated zone state (the intake checked node, zone and seq); True if zone costs changed."""
        view = self._nodes.get(msg.node)
        if view is None or view.zone != msg.zone:
            return False
        self._tick(received_at)
        view.state = msg.state
        view.heard_at = received_at
        view.online = True
        self._arm(msg.node, view)
        return self._reevaluate(view.zone)

    def on_node_status(self, msg: NodeStatus, received_at: float) -> bool:
        """Birth (`online`) or will (`offline`); an offline node is stale at once."""
        view = self._nodes.get(msg.node)
        if view is None:
            return False
        self._tick(received_at)
        view.online = msg.status == "online"
        if view.online:
            view.heard_at = received_at
            self._arm(msg.node, view)
        else:
            self._due.pop(msg.node, None)  # stale at once; nothing to wait for
        return self._reevaluate(view.zone)

    def restore(self, node: str, state: str, heard_at: float, online: bool, now: float) -> bool:
        """A node's last known state from before a restart (zones.last_known), heard at `heard_at`: read at `now`
        under the stale policy as if it had never stopped; True if zone costs changed."""
        view = self._nodes.get(node)
        if view is None:
            return False
        self._tick(now)
        view.state = state
        view.heard_at = min(heard_at, now)
        view.online = online
        self._due.pop(node, None)
        self._arm(node, view)
        return self._reevaluate(view.zone)

    def on_operator_block(self, block_id: str, msg: OperatorBlock | None, received_at: float) -> bool:
        """Set (or with None remove) an operator block; a block on an unknown zone is ignored."""
        self._tick(received_at)
        self._blocks.pop(block_id, None)
        if msg is not None:
            if msg.zone is not None:
                if msg.zone not in self._windows:
                    return self._reevaluate()
                self._blocks[block_id] = _Block(msg.zone, None, msg.expires_at)
            else:
                assert msg.polygon is not None
                window = polygon_window(msg.polygon, self.frame)
                self._blocks[block_id] = _Block(None, window, msg.expires_at)
        return self._reevaluate()

    def refresh(self, now: float) -> bool:
        """Age the nodes (staleness) and expire operator blocks at `now`; True if zone costs changed.

        Incremental: only the zones of nodes whose staleness deadline passed are evaluated again (a heap of
        deadlines), and every zone only when an operator block expired; the result is what evaluating every
        zone would give, at O(changes) instead of O(zones), so the console can ask it for each message."""
        self._tick(now)
        if any(b.expires_at is not None and now >= b.expires_at for b in self._blocks.values()):
            return self._reevaluate()
        zones: set[str] = set()
        heap = self._deadlines
        while heap and heap[0][0] < now:
            deadline, node = heapq.heappop(heap)
            if self._due.get(node) == deadline:
                del self._due[node]
                zones.add(self._nodes[node].zone)
        if not zones:
            return False
        zone_blocked = {b.zone for b in self._blocks.values()}
        changed = False
        for zone in zones:
            changed |= self._update_zone(zone, zone_blocked)
        return changed

    # -- outputs --------------------------------------------------------------------------------------------

    def zone_costs(self) -> dict[str, int]:
        """Effective cost per zone id: 0 clear, caution cost, LETHAL (254) or NO_INFORMATION (255)."""
        return dict(self._costs)

    def blocked_zones(self) -> list[str]:
        """Zone ids treated as lethal now (blocked, operator-blocked, or stale under the lethal policy)."""
        return [z for z in self._zone_ids if self._costs[z] == LETHAL_OBSTACLE]

    def active_blocks(self) -> list[str]:
        """Operator block ids in force now (zone or polygon)."""
        return sorted(self._blocks)

    def zone_word(self, zone_id: str) -> Word:
        """What the robots make of a zone now, by the one rule (operator block, staleness, fusion): the
        console shows this, so the operator's map is what the robots avoid."""
        if any(b.zone == zone_id for b in self._blocks.values()):
            return "blocked"
        return self._fuse([self._word(self._nodes[n]) for n in self._watchers[zone_id]])

    def stale_nodes(self, zone_id: str) -> list[str]:
        """The zone's nodes that are silent past the policy's limit or offline (read by `policy.stale`)."""
        return [n for n in self._watchers[zone_id] if self._stale(self._nodes[n])]

    def zone_window(self, zone_id: str) -> CellWindow:
        return self._windows[zone_id]

    def block_window(self, block_id: str) -> CellWindow | None:
        """The cells of an operator polygon block in force, or None (zone blocks use the zone's window)."""
        block = self._blocks.get(block_id)
        return block.window if block is not None else None

    def blocked_areas(self) -> list[tuple[BlockedArea, CellWindow]]:
        """Every lethal area with its cells: blocked zones, then operator polygon blocks in force."""
        out = [(BlockedArea("zone", z), self._windows[z]) for z in self.blocked_zones()]
        for block_id in self.active_blocks():
            window = self.block_window(block_id)
            if window is not None:
                out.append((BlockedArea("block", block_id), window))
        return out

    def take_changes(self) -> list[Bounds]:
        """The cell windows whose zone cost changed since the last call (the costmap repaints only these)."""
        out = [b for b in self._pending.values() if not b.empty]
        self._pending.clear()
        return out

    def paint(
        self, bounds: Bounds, exclude: Collection[BlockedArea] = (), outside: int = FREE_SPACE
    ) -> NDArray[np.uint8]:
        """The zone layer's costs inside `bounds` (numeric maximum where areas overlap; `outside` in cells no
        area covers: FREE_SPACE for the ROS grid, NO_INFORMATION for the costmap's merge, which skips them).

        `exclude` leaves out blocked areas: what the layer would paint without the areas a robot stands in, so it
        can be let out of them.
        """
        out = np.zeros(bounds.shape, dtype=np.uint8)
        covered = np.zeros(bounds.shape, dtype=bool)
        for zone_id, cost in self._costs.items():
            if BlockedArea("zone", zone_id) not in exclude:
                self._paint_window(out, covered, bounds, self._windows[zone_id], cost)
        for block_id, window in self._polys.items():
            if BlockedArea("block", block_id) not in exclude:
                self._paint_window(out, covered, bounds, window, LETHAL_OBSTACLE)
        if outside != FREE_SPACE:
            out[~covered] = outside
        return out

    # -- internals ------------------------------------------------------------------------------------------

    @staticmethod
    def _paint_window(
        out: NDArray[np.uint8], covered: NDArray[np.bool_], bounds: Bounds, window: CellWindow, cost: int
    ) -> None:
        if window.empty:
            return
        area = Bounds.of_window(window)
        common = area.intersection(bounds)
        if common.empty:
            return
        dst = out[common.within(bounds)]
        src = window.mask[common.within(area)]
        np.maximum(dst, np.where(src, np.uint8(cost), np.uint8(0)), out=dst)
        covered[common.within(bounds)] |= src

    def _tick(self, t: float) -> None:
        if self._started is None:
            self._started = t
            for node, view in self._nodes.items():  # a node never heard turns stale counting from here
                self._arm(node, view)
        self._now = t if self._now is None else max(self._now, t)

    def _arm(self, node: str, view: _NodeView) -> None:
        """Remember when `node` turns stale if it says nothing more (`_stale`'s rule, as a point in time)."""
        deadline = self._stale_at(view)
        if deadline is None or not view.online:
            return
        self._due[node] = deadline
        heapq.heappush(self._deadlines, (deadline, node))
        if len(self._deadlines) > 4 * len(self._nodes) + 64:  # outdated entries: rebuild from the live ones
            self._deadlines = [(d, n) for n, d in self._due.items()]
            heapq.heapify(self._deadlines)

    def _mark(self, key: AreaKey, window: CellWindow) -> None:
        bounds = Bounds.of_window(window)
        self._pending[key] = bounds.union(self._pending.get(key))

    def _stale(self, view: _NodeView) -> bool:
        if not view.online:
            return True
        deadline = self._stale_at(view)
        return self._now is not None and deadline is not None and self._now > deadline

    def _stale_at(self, view: _NodeView) -> float | None:
        """When an online node turns stale if it says nothing more: one expression for `_stale` and the heap,
        so both round alike."""
        since = view.heard_at if view.heard_at is not None else self._started
        return None if since is None else since + self.policy.stale_after_heartbeats * view.heartbeat_s

    def _word(self, view: _NodeView) -> Word:
        fresh: Word = "clear" if view.state is None else _as_word(view.state)
        if not self._stale(view):
            return fresh
        match self.policy.stale:
            case "keep":
                return fresh
            case "unknown":
                return "unknown"
            case "lethal":
                return "blocked"

    def _fuse(self, words: list[Word]) -> Word:
        if not words:
            return "clear"
        if self.policy.fuse == "any_blocked":
            return max(words, key=_RANK.__getitem__)
        # majority: blocked only when more than half the zone's nodes say so; a minority report is a caution
        blocked = words.count("blocked")
        if 2 * blocked > len(words):
            return "blocked"
        if 2 * words.count("unknown") > len(words):
            return "unknown"
        return "caution" if blocked or "caution" in words else "clear"

    def _cost(self, word: Word) -> int:
        match word:
            case "clear":
                return FREE_SPACE
            case "caution":
                return self.policy.caution_cost
            case "unknown":
                return NO_INFORMATION
            case "blocked":
                return LETHAL_OBSTACLE

    def _reevaluate(self, zone_id: str | None = None) -> bool:
        """Recompute one zone's cost (a message from its node), or every zone's and the blocks in force (a
        refresh, an operator block); remember the areas that changed. One zone only keeps a message O(1) when
        a thousand nodes report every second."""
        if zone_id is not None:
            return self._update_zone(zone_id, {b.zone for b in self._blocks.values()})
        now = self._now
        if now is not None:
            for block_id, block in list(self._blocks.items()):
                if block.expires_at is not None and now >= block.expires_at:
                    del self._blocks[block_id]
        zone_blocked = {b.zone for b in self._blocks.values()}
        changed = False
        for zone in self._zone_ids:
            changed |= self._update_zone(zone, zone_blocked)
        polys = {i: b.window for i, b in self._blocks.items() if b.window is not None}
        for block_id in polys.keys() | self._polys.keys():
            before, after = self._polys.get(block_id), polys.get(block_id)
            if before is after:
                continue
            for window in (before, after):
                if window is not None:
                    self._mark(("block", block_id), window)
            changed = True
        self._polys = polys
        return changed

    def _update_zone(self, zone_id: str, zone_blocked: set[str | None]) -> bool:
        if zone_id in zone_blocked:
            cost = LETHAL_OBSTACLE
        else:
            cost = self._cost(self._fuse([self._word(self._nodes[n]) for n in self._watchers[zone_id]]))
        if cost == self._costs[zone_id]:
            return False
        self._costs[zone_id] = cost
        self._mark(("zone", zone_id), self._windows[zone_id])
        return True


def _as_word(state: str) -> Word:
    if state == "blocked":
        return "blocked"
    if state == "caution":
        return "caution"
    return "clear"
