"""amqtt's table of subscriptions (filter -> subscribers), able to say which filters match a topic without a scan.

amqtt 0.12.1 matches every published message against every filter any client holds: on a site each node
subscribes to its own command topic, so 1000 nodes at 1 Hz cost a million filter comparisons a second (each
building a debug line it then discards). Exact filters are looked up by key here, and only the few wildcard
filters (robots' `zones/#`, the console's) are compared. It is a dict, so amqtt's own code keeps using it as one.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

Subscribers = list[tuple[Any, int]]
"""(amqtt Session, granted QoS) for each client holding a filter."""


def is_wildcard(topic_filter: str) -> bool:
    return "+" in topic_filter or "#" in topic_filter


class SubscriptionIndex(dict[str, Subscribers]):
    """A dict of filter -> subscribers that also keeps its wildcard filters apart, in insertion order."""

    def __init__(self, items: Iterable[tuple[str, Subscribers]] = ()) -> None:
        super().__init__()
        self._wildcards: dict[str, None] = {}
        for key, value in items:
            self[key] = value

    def __setitem__(self, key: str, value: Subscribers) -> None:
        super().__setitem__(key, value)
        if is_wildcard(key):
            self._wildcards[key] = None

    def __delitem__(self, key: str) -> None:
        super().__delitem__(key)
        self._wildcards.pop(key, None)

    def pop(self, key: str, *default: Any) -> Any:  # type: ignore[override]
        self._wildcards.pop(key, None)
        return super().pop(key, *default)

    def popitem(self) -> tuple[str, Subscribers]:
        key, value = super().popitem()
        self._wildcards.pop(key, None)
        return key, value

    def setdefault(self, key: str, default: Subscribers | None = None) -> Subscribers:  # type: ignore[override]
        if key not in self:
            self[key] = default if default is not None else []
        return self[key]

    def update(self, *args: Any, **kwargs: Any) -> None:
        for key, value in dict(*args, **kwargs).items():
            self[key] = value

    def clear(self) -> None:
        super().clear()
        self._wildcards.clear()

    def __ior__(self, other: Any) -> SubscriptionIndex:  # type: ignore[override]
        self.update(other)
        return self

    def wildcards(self) -> Iterator[str]:
        """The wildcard filters held now (a copy: the caller may change the table while it goes through them)."""
        return iter(tuple(self._wildcards))

    def matching(self, topic: str, matches: Callable[[str, str], bool]) -> list[tuple[str, Subscribers]]:
        """(filter, subscribers) for every filter that matches `topic`: the exact one by key, the wildcard ones
        by `matches(topic, filter)` (amqtt's own matcher, so `$` topics and malformed filters behave as before)."""
        found: list[tuple[str, Subscribers]] = []
        exact = self.get(topic)
        if exact is not None and not is_wildcard(topic):
            found.append((topic, exact))
        for topic_filter in self.wildcards():
            subscribers = self.get(topic_filter)
            if subscribers is not None and matches(topic, topic_filter):
                found.append((topic_filter, subscribers))
        return found
