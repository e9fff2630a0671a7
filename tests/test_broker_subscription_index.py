"""wsnav.broker.amqtt.subscription_index: the filters it finds for a topic are the ones amqtt's own scan finds.

amqtt 0.12.1 compared each published topic with every filter held (1000 nodes' command topics at 1000 messages
a second); the index looks the exact filter up by key and compares only the wildcard ones. Checked here against
amqtt's matcher over every filter, with filters added and removed the ways amqtt's code changes its table.
"""

from __future__ import annotations

import logging
import random
from types import SimpleNamespace

from amqtt.broker import Broker

from wsnav.broker.amqtt.subscription_index import SubscriptionIndex

LEVELS = ["wsn", "s", "zones", "z1", "z2", "state", "n1", "n2", "nodes", "command", "$SYS"]


def _matches(topic: str, a_filter: str) -> bool:
    """amqtt's matcher (it needs only a logger of its broker)."""
    broker = SimpleNamespace(logger=logging.getLogger("test"))
    return Broker._matches(broker, topic, a_filter)  # type: ignore[arg-type]  # pyright: ignore[reportPrivateUsage, reportArgumentType]


def _filter(rng: random.Random) -> str:
    levels = [rng.choice([*LEVELS, "+", "+"]) for _ in range(rng.randint(1, 5))]
    if rng.random() < 0.3:
        levels.append("#")
    return "/".join(levels)


def _topic(rng: random.Random) -> str:
    return "/".join(rng.choice(LEVELS) for _ in range(rng.randint(1, 5)))


def test_the_index_finds_exactly_the_filters_amqtts_scan_finds() -> None:
    rng = random.Random(37)
    table = SubscriptionIndex()
    for step in range(3000):
        action = rng.random()
        if action < 0.5:
            table[_filter(rng) if rng.random() < 0.6 else _topic(rng)] = [(object(), 1)]
        elif action < 0.7 and table:
            del table[rng.choice(list(table))]
        elif action < 0.75 and table:
            table.pop(rng.choice(list(table)))
        elif action < 0.76:
            table.clear()
        topic = _topic(rng)
        found = {f for f, _ in table.matching(topic, _matches)}
        scanned = {f for f in table if _matches(topic, f)}
        assert found == scanned, (step, topic, found ^ scanned)
    assert set(table.wildcards()) == {f for f in table if "+" in f or "#" in f}
