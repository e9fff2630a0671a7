"""BENCHMARKS.md, where each benchmark owns one section (a `## ` heading to the next) and rewrites only that;
also what every benchmark's section and command line share (the machine it ran on, `--no-write`)."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import time
from pathlib import Path

BENCHMARKS_MD = Path(__file__).resolve().parent.parent / "BENCHMARKS.md"


def write_section(heading: str, text: str, path: Path = BENCHMARKS_MD) -> None:
    """Replace the section under `heading` (a full `## ...` line) with `text`, or append it if absent."""
    current = path.read_text()
    pattern = re.compile(rf"^{re.escape(heading)}\n.*?(?=^## |\Z)", re.S | re.M)
    block = f"{heading}\n\n{text.rstrip()}\n\n"
    updated = (
        pattern.sub(lambda _: block, current)
        if pattern.search(current)
        else current.rstrip() + "\n\n" + block
    )
    path.write_text(updated.rstrip() + "\n")


def bench_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's parser: its docstring's first line as description, and `--no-write` to print only."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0] if doc else None)
    parser.add_argument("--no-write", action="store_true", help="print only; leave BENCHMARKS.md alone")
    return parser


def commit() -> str:
    """The commit measured (with `+dirty` when the tree has changes): a section names the code it measured."""
    here = Path(__file__).resolve().parent
    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True)
    dirty = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True)
    return (rev.stdout.strip() or "unknown") + ("+dirty" if dirty.stdout.strip() else "")


def machine_note() -> str:
    """`N CPUs, load L, measured DATE`: what a reader needs to weigh the numbers, sampled when the section is written."""
    return f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}, measured {time.strftime('%Y-%m-%d')}"
