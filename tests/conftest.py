"""Shared test fixtures: the repo's paths and the rule for tests that need a system tool."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SITES = REPO / "sites"


def require_tool(name: str) -> str:
    """Path of a system tool; skip when missing, but fail under WSNAV_REQUIRE_TOOLS=1 (CI)."""
    path = shutil.which(name)
    if path is None:
        if os.environ.get("WSNAV_REQUIRE_TOOLS") == "1":
            pytest.fail(f"system tool {name!r} is required (WSNAV_REQUIRE_TOOLS=1) but not on PATH")
        pytest.skip(f"system tool {name!r} not installed")
    return path


pytest_plugins = ["tests.ros_fixtures"]
