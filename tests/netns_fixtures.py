"""Two network namespaces of our own joined by a veth pair: a broker's and its nodes', as on a site's network.

One namespace holds the broker (`PREFIX.1`); the other holds the nodes, each on its own address (`PREFIX.2`,
`PREFIX.3`...), so a per-source firewall rule (`wsnav broker firewall`) applies to them as it would at a site,
where loopback would put every client on one address. Used by tests/test_broker_firewall.py and the broker
benchmarks (bench.mosquitto_flood_firewall, bench.attack_latency), which import fixture modules, never test
modules. Needs root and `ip`; the rule itself needs `nft`.

A process enters a namespace by `ip netns exec NS ...` (`exec_in`), or one thread of ours by setns(2)
(`in_namespace`): a socket belongs to the namespace of the thread that made it, so a paho client connected
there stays there while its network thread runs anywhere.
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TypeVar

T = TypeVar("T")

_CLONE_NEWNET = 0x40000000


class NamespaceError(RuntimeError):
    """The namespaces could not be made here (not root, no `ip`, no veth): one line saying why."""


@dataclass(frozen=True)
class NamespacePair:
    broker: str
    nodes: str
    prefix: str
    """The /24 both sides share, as `10.99.37` (the broker is `.1`, nodes `.2` and up)."""

    @property
    def broker_address(self) -> str:
        return f"{self.prefix}.1"

    def node_address(self, k: int) -> str:
        """The k-th node address (k = 1, 2...)."""
        return f"{self.prefix}.{k + 1}"

    @property
    def subnet(self) -> str:
        return f"{self.prefix}.0/24"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@contextmanager
def namespace_pair(prefix: str, tag: str, node_addresses: int = 2) -> Iterator[NamespacePair]:
    """Make the pair (named `wsnav-<tag>b<pid>` and `wsnav-<tag>n<pid>`), yield it, delete it whatever happens.

    Raises NamespaceError when it cannot be made."""
    pid = os.getpid()
    pair = NamespacePair(f"wsnav-{tag}b{pid}", f"wsnav-{tag}n{pid}", prefix)
    veth = f"w{tag}{pid % 100000}"
    try:
        try:
            _ip("netns", "add", pair.broker)
            _ip("netns", "add", pair.nodes)
            _ip("link", "add", f"{veth}a", "type", "veth", "peer", "name", f"{veth}b")
            _ip("link", "set", f"{veth}a", "netns", pair.broker)
            _ip("link", "set", f"{veth}b", "netns", pair.nodes)
            _ip("-n", pair.broker, "addr", "add", f"{pair.broker_address}/24", "dev", f"{veth}a")
            for k in range(1, node_addresses + 1):
                _ip("-n", pair.nodes, "addr", "add", f"{pair.node_address(k)}/24", "dev", f"{veth}b")
            for ns, dev in ((pair.broker, f"{veth}a"), (pair.nodes, f"{veth}b")):
                _ip("-n", ns, "link", "set", dev, "up")
                _ip("-n", ns, "link", "set", "lo", "up")
        except subprocess.CalledProcessError as exc:
            raise NamespaceError(
                f"cannot make network namespaces here: {exc.stderr.decode(errors='replace').strip()}"
            ) from None
        except FileNotFoundError:
            raise NamespaceError("cannot make network namespaces here: no `ip` command") from None
        yield pair
    finally:
        for ns in (pair.broker, pair.nodes):
            subprocess.run(["ip", "netns", "del", ns], check=False, capture_output=True)


def exec_in(ns: str) -> list[str]:
    """The prefix that runs a command in namespace `ns`."""
    return ["ip", "netns", "exec", ns]


def enter_namespace(ns: str) -> None:
    """Move the calling thread into namespace `ns` (threads it starts later are there too)."""
    fd = os.open(f"/var/run/netns/{ns}", os.O_RDONLY)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.setns(fd, _CLONE_NEWNET) != 0:
            raise NamespaceError(f"setns({ns}): {os.strerror(ctypes.get_errno())}")
    finally:
        os.close(fd)


def in_namespace(ns: str, make: Callable[[], T]) -> T:
    """`make()` run on a thread inside namespace `ns` (what it connects lives there); its result or its error."""
    result: list[T] = []
    error: list[BaseException] = []

    def run() -> None:
        try:
            enter_namespace(ns)
            result.append(make())
        except BaseException as exc:  # handed to the caller
            error.append(exc)

    thread = threading.Thread(target=run, name=f"netns-{ns}")
    thread.start()
    thread.join()
    if error:
        raise error[0]
    return result[0]
