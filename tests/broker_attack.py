"""An outsider's attack on a broker's port, run as its own process: `python -m tests.broker_attack ...`.

- `idle N HOLD`: open N TCP connections that never send a byte, keep them HOLD seconds, close them;
- `churn N`: N connect-and-close cycles.
Both are bounded (at most N sockets, every connect times out after 3 s) and stop by themselves. Loopback only.
Prints one line with what it managed, for the test's failure messages.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import resource
import socket


async def _open(port: int) -> socket.socket | None:
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setblocking(False)
    try:
        await asyncio.wait_for(loop.sock_connect(sock, ("127.0.0.1", port)), 3.0)
        return sock
    except (OSError, TimeoutError):
        sock.close()
        return None


async def idle(port: int, count: int, hold_s: float) -> str:
    opened: list[socket.socket] = []
    for start in range(0, count, 100):  # batches: the listen backlog is 100
        batch = await asyncio.gather(*(_open(port) for _ in range(start, min(count, start + 100))))
        opened += [s for s in batch if s is not None]
    await asyncio.sleep(hold_s)
    for sock in opened:
        with contextlib.suppress(OSError):
            sock.close()
    return f"idle: {len(opened)}/{count} connected"


async def churn(port: int, count: int) -> str:
    done = 0
    for start in range(0, count, 50):
        batch = await asyncio.gather(*(_open(port) for _ in range(start, min(count, start + 50))))
        for sock in batch:
            if sock is not None:
                done += 1
                sock.close()
    return f"churn: {done}/{count} connected and closed"


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["idle", "churn"])
    parser.add_argument("port", type=int)
    parser.add_argument("count", type=int)
    parser.add_argument("hold", type=float, nargs="?", default=0.0)
    args = parser.parse_args()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, max(soft, args.count + 256)), hard))
    if args.mode == "idle":
        print(asyncio.run(idle(args.port, args.count, args.hold)), flush=True)
    else:
        print(asyncio.run(churn(args.port, args.count)), flush=True)


if __name__ == "__main__":
    main()
