"""Every state change reaches the page, however the messages are batched: heartbeats may be coalesced, state
changes never. With 1000 nodes on a loaded machine the console read messages in bursts, and a node that went
`clear` and back to `blocked` within one batch showed `blocked` throughout (bench.console_feed: 60-76 % of a
probe node's changes shown). Here node s1 says blocked, clear, blocked back to back, on a real broker, and the
console's own event stream (what the page reads) is followed."""

from __future__ import annotations

import base64
import contextlib
import json
import threading
import time
import urllib.request
from pathlib import Path

import pytest

from tests.console_fixtures import NodeS1, start_console, until
from tests.stack_fixtures import make_site, stack_on

pytestmark = pytest.mark.timeout(120)


def follow(url: str, password: str, seen: list[tuple[str, str]], stop: threading.Event) -> None:
    """(event type, s1's state) of every entry of node s1 on the console's event stream."""
    req = urllib.request.Request(url + "/api/events")
    req.add_header("Authorization", "Basic " + base64.b64encode(f"operator:{password}".encode()).decode())
    with contextlib.suppress(OSError), urllib.request.urlopen(req, timeout=30) as stream:
        for raw in stream:
            if stop.is_set():
                return
            line = raw.decode().strip()
            if not line.startswith("data: "):
                continue
            event = json.loads(line[6:])
            seen += [(event["type"], n["state"]) for n in event.get("nodes", []) if n["id"] == "s1"]


def test_a_node_that_changes_twice_within_one_batch_shows_each_change(tmp_path: Path) -> None:
    with stack_on(make_site(tmp_path / "site"), tmp_path) as stack:
        stack.broker()
        node = NodeS1(stack)
        node.say("clear")
        _console, url = start_console(stack)
        password = json.loads((stack.creds / "operator.json").read_text())["password"]
        seen: list[tuple[str, str]] = []
        stop = threading.Event()
        reader = threading.Thread(target=follow, args=(url, password, seen, stop), daemon=True)
        reader.start()
        try:
            until(
                "the page shows s1 clear",
                lambda: ("snapshot", "clear") in seen or ("update", "clear") in seen,
            )
            for _ in range(3):  # three tries: the three messages must land in one batch of the console's
                start = len(seen)
                for state in ("blocked", "clear", "blocked"):
                    node.say(state)
                until("s1 blocked on the page", lambda s=start: ("update", "blocked") in seen[s:])
                time.sleep(0.5)
                shown = [state for kind, state in seen[start:] if kind == "update"]
                changes = [s for i, s in enumerate(shown) if i == 0 or shown[i - 1] != s]
                assert changes == ["blocked", "clear", "blocked"], f"the page was shown {shown}"
                node.say("clear")
                until("s1 clear again", lambda s=start: seen[-1][1] == "clear" and len(seen) > s)
        finally:
            stop.set()
            node.close()
