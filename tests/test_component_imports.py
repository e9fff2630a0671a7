"""The layering docs/architecture.md describes, read from the source: no component imports the wsnav CLI, and robot_agent and
zone_sim never import each other (a violation would tie a robot's install to the CLI or to the simulator)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

COMPONENTS = [
    "broker",
    "firmware",
    "robot_agent",
    "zone_sim",
    "schemas",
    "runtime",
    "experiments",
    "ros_bridge",
    "console",
]
FORBIDDEN = {
    "robot_agent": {"zone_sim", "ros_bridge"},  # the agent runs where no ROS is installed
    "zone_sim": {"robot_agent", "ros_bridge"},
    "ros_bridge": {"zone_sim"},
    "console": {"robot_agent", "zone_sim", "ros_bridge", "experiments"},  # only the MQTT contract
}


def imported_packages(source: Path) -> set[str]:
    """Top-level packages a module imports, also inside functions and TYPE_CHECKING blocks."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(source.read_text(), filename=str(source))):
        if isinstance(node, ast.Import):
            out.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


@pytest.mark.parametrize("component", COMPONENTS)
def test_a_component_imports_neither_the_cli_nor_a_sibling_it_must_not_know(component: str) -> None:
    forbidden = {"wsnav"} | FORBIDDEN.get(component, set())
    sources = [p for p in (REPO / component).rglob("*.py") if "device" not in p.relative_to(REPO).parts]
    assert sources
    bad = {
        f"{p.relative_to(REPO)} imports {pkg}" for p in sources for pkg in imported_packages(p) & forbidden
    }
    assert not bad, sorted(bad)


def test_every_component_ships_in_the_wheel_and_the_image() -> None:
    """A component missing from the package list or the image's build context installs, then fails to import."""
    import tomllib

    include = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"][
        "include"
    ]
    context = (REPO / ".dockerignore").read_text().splitlines()
    for component in [*COMPONENTS, "wsnav"]:
        assert f"{component}*" in include, f"pyproject.toml: {component} is not in the packages"
        assert f"!{component}/" in context, f".dockerignore: {component}/ is left out of the image"
