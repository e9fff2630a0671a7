"""BENCHMARKS.md, where each benchmark owns one section (a `## ` heading to the next) and rewrites only that."""

from __future__ import annotations

import re
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
