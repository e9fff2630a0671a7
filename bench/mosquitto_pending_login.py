"""Mosquitto's login time with the pending-password plugin (broker/mosquitto/pending_auth.c) against without it.

Debian's Mosquitto 2.0 from `wsnav broker mosquitto-config` for the school site, one process per condition, the
same machine: a node's login (raw MQTT CONNECT to CONNACK, then DISCONNECT; one socket after another, a random
0-5 ms pause between them so no sample locks onto a periodic peer) under
- no plugin (the baseline, measured in the same run);
- the plugin with an empty pending file (no change under way: every login is read from the file, then deferred);
- the plugin with a pending password for every node of the site (a site-wide change under way): a node logging
  in with its own password (the plugin checks the node's pending line first, one PBKDF2, then defers) and with
  its pending one.
Conditions take turns in rounds, so a change of the machine's load falls on each alike. Prints median and p99 per
condition and each median over the baseline's; writes its section of BENCHMARKS.md unless --no-write.
`--quick`: fewer logins; each median over the baseline's at most 5.
"""

from __future__ import annotations

import os
import random
import socket
import statistics
import subprocess
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

from bench.benchmarks_md import commit, machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from wsnav.broker.credentials import new_password, write_credentials
from wsnav.broker.mosquitto import pending
from wsnav.broker.mosquitto.config import CONF, MosquittoOptions, write_mosquitto_config
from wsnav.broker.mosquitto.process import free_port
from wsnav.schemas.credentials import load_credentials
from wsnav.schemas.site import load_site

SECTION = "## Mosquitto: login time with the pending-password plugin"
COMMAND = "./.venv/bin/python -m bench.mosquitto_pending_login"
SITE = Path(__file__).resolve().parent.parent / "sites" / "school"


def _string(text: str) -> bytes:
    data = text.encode()
    return len(data).to_bytes(2, "big") + data


def connect_packet(user: str, password: str) -> bytes:
    """MQTT 3.1.1 CONNECT, clean session, username and password."""
    body = _string("MQTT") + bytes([4, 0xC2]) + (30).to_bytes(2, "big")
    body += _string(user) + _string(user) + _string(password)
    length, n = b"", len(body)
    while True:
        byte, n = n % 128, n // 128
        length += bytes([byte | (128 if n else 0)])
        if not n:
            break
    return b"\x10" + length + body


def login_s(port: int, packet: bytes) -> float:
    """Seconds from connect() to CONNACK; asserts the broker accepted."""
    t0 = time.perf_counter()
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(packet)
        ack = b""
        while len(ack) < 4:
            chunk = s.recv(4 - len(ack))
            assert chunk, "the broker closed the connection"
            ack += chunk
        took = time.perf_counter() - t0
        assert ack[0] == 0x20 and ack[3] == 0, f"login refused: {ack!r}"
        s.sendall(b"\xe0\x00")
    return took


@dataclass
class Condition:
    name: str
    port: int
    packets: list[bytes]
    samples: list[float]


def start(root: Path, creds: Path, plugin: bool) -> tuple[subprocess.Popen[bytes], int, Path]:
    port = free_port()
    user = "root" if os.geteuid() == 0 else None
    conf = root / "mq"
    options = MosquittoOptions(bind=("127.0.0.1", port), data_dir=root / "data", user=user)
    write_mosquitto_config(load_site(SITE).spec, creds, conf, replace(options, pending_passwords=plugin))
    proc = subprocess.Popen(["mosquitto", "-c", str(conf / CONF)], stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 30
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return proc, port, conf
        except OSError:
            assert time.monotonic() < deadline and proc.poll() is None, "mosquitto did not start"
            time.sleep(0.05)


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--logins", type=int, default=2000, help="logins per condition (default 2000)")
    args = parse_quick_args(parser)
    if args.quick:
        args.logins = 150
    spec = load_site(SITE).spec
    nodes = [n.id for n in spec.nodes]
    procs: list[subprocess.Popen[bytes]] = []
    with tempfile.TemporaryDirectory(prefix="wsnav-mq-pending-") as tmp_name:
        tmp = Path(tmp_name)
        creds = tmp / "creds"
        write_credentials(spec, creds)
        own = {n: connect_packet(n, load_credentials(creds / f"{n}.json").password) for n in nodes}
        try:
            base, base_port, _ = start(tmp / "base", creds, plugin=False)
            empty, empty_port, _ = start(tmp / "empty", creds, plugin=True)
            full, full_port, full_conf = start(tmp / "full", creds, plugin=True)
            procs += [base, empty, full]
            fresh = {n: new_password() for n in nodes}
            for n in nodes:
                pending.add(full_conf, n, fresh[n])
            conditions = [
                Condition("no plugin (baseline)", base_port, list(own.values()), []),
                Condition("plugin, no pending password", empty_port, list(own.values()), []),
                Condition(
                    f"plugin, {len(nodes)} pending: a node's own password", full_port, list(own.values()), []
                ),
                Condition(
                    f"plugin, {len(nodes)} pending: a node's pending password",
                    full_port,
                    [connect_packet(n, fresh[n]) for n in nodes],
                    [],
                ),
            ]
            rng = random.Random(1)
            for c in conditions:  # warm-up, not counted
                for p in c.packets[:5]:
                    login_s(c.port, p)
            for i in range(args.logins):
                for c in conditions:
                    c.samples.append(login_s(c.port, c.packets[i % len(c.packets)]))
                    time.sleep(rng.uniform(0, 0.005))
        finally:
            for p in procs:
                p.terminate()
                p.wait(30)
    base_median = statistics.median(conditions[0].samples)
    rows = []
    for c in conditions:
        med = statistics.median(c.samples)
        p99 = statistics.quantiles(c.samples, n=100)[98]
        rows.append(f"| {c.name} | {med * 1e3:.3f} | {p99 * 1e3:.3f} | {med / base_median:.2f} |")
        print(
            f"{c.name}: median {med * 1e3:.3f} ms, p99 {p99 * 1e3:.3f} ms, {med / base_median:.2f}x",
            flush=True,
        )
    if args.quick:
        for c in conditions[1:]:
            check_ratio(
                f"login median, {c.name}, over no plugin", statistics.median(c.samples) / base_median, 5.0
            )
        finish_quick()
    text = (
        f"{machine_note()}, commit {commit()}. Debian's Mosquitto 2.0.11, one process per condition, "
        f"{args.logins} logins each (conditions in turn, a random 0-5 ms pause between logins), a node's MQTT "
        "CONNECT to its CONNACK over loopback. The plugin reads its pending file at each login and checks the "
        "node's pending line (PBKDF2-SHA512, 101 iterations, as the password file) before it defers to the "
        "password file.\n\n"
        "| condition | median, ms | p99, ms | median over no plugin |\n| --- | ---: | ---: | ---: |\n"
        + "\n".join(rows)
        + f"\n\nReproduce: `{COMMAND}` (`--logins N`; `--quick`)."
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
