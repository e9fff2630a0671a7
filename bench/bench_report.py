"""What every benchmark here shares: percentiles, and replacing its own section of BENCHMARKS.md."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent


def percentile_ms(samples_s: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(samples_s) * 1000.0, q))


def write_section(section: str, text: str) -> None:
    """Replace (or append) the `## ...` section titled `section` in BENCHMARKS.md, leaving the others alone."""
    path = REPO / "BENCHMARKS.md"
    current = path.read_text()
    pattern = re.compile(rf"^{re.escape(section)}\n.*?(?=^## |\Z)", re.S | re.M)
    block = f"{section}\n\n{text.rstrip()}\n\n"
    updated = (
        pattern.sub(lambda _: block, current)
        if pattern.search(current)
        else current.rstrip() + "\n\n" + block
    )
    path.write_text(updated.rstrip() + "\n")
