"""Every benchmark's quick mode (`--quick`): a minute or less, each ratio compared with its bound, and the exit
that CI reads (0 all within bounds; 1 after a `REGRESSION:` line per ratio beyond its bound; 2 bad arguments).

A ratio is a figure over a baseline measured in the same run (a bounded update over a rebuild, a plan over a
reference plan), oriented so that bigger is worse; its bound is wide enough for a loaded 2-core machine and tight
enough to catch a 5x regression. A quick run prints its figures as usual and never writes BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from typing import NoReturn

from bench.benchmarks_md import bench_parser


@dataclass(frozen=True)
class RatioCheck:
    """One ratio of a quick run against its bound."""

    name: str
    value: float
    bound: float

    @property
    def within(self) -> bool:
        return self.value <= self.bound


_checks: list[RatioCheck] = []
"""The ratios this process has checked, in order (one benchmark per process)."""


def quick_parser(doc: str | None) -> argparse.ArgumentParser:
    """A benchmark's parser (`--no-write`) with `--quick`, which implies `--no-write`."""
    parser = bench_parser(doc)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="run in a minute or less, check each ratio against its bound, exit 1 on a regression; writes nothing",
    )
    return parser


def parse_quick_args(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """Parse, with `--quick` turning on `--no-write` (a quick run's small sample is not a published figure)."""
    args = parser.parse_args(argv)
    if getattr(args, "quick", False):
        args.no_write = True
    return args


def check_ratio(name: str, value: float, bound: float) -> bool:
    """Print a ratio with its bound and record it; True when within (value <= bound)."""
    check = RatioCheck(name, float(value), float(bound))
    _checks.append(check)
    print(
        f"quick: {name} = {check.value:.3g} (bound {check.bound:.3g}){'' if check.within else '  <-- beyond'}"
    )
    return check.within


def regressions() -> list[RatioCheck]:
    """The ratios recorded so far that went beyond their bound."""
    return [c for c in _checks if not c.within]


def finish_quick() -> NoReturn:
    """Exit as CI reads it: 1 after one `REGRESSION:` line per ratio beyond its bound, else 0."""
    bad = regressions()
    for c in bad:
        print(f"REGRESSION: {c.name} = {c.value:.3g}, bound {c.bound:.3g}", flush=True)
    if not _checks:
        print("REGRESSION: quick mode checked no ratio", flush=True)
        sys.exit(1)
    sys.exit(1 if bad else 0)


def quick_skipped(why: str) -> NoReturn:
    """A benchmark that cannot be made quick (its docstring says why): one line, exit 0."""
    print(f"quick: skipped ({why})", flush=True)
    sys.exit(0)
