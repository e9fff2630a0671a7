"""The layering docs/architecture.md describes, read from the source: no component imports the wsnav CLI, and robot_agent and
zone_sim never import each other (a violation would tie a robot's install to the CLI or to the simulator)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO

ALLOWED: dict[str, set[str]] = {
    "schemas": set(),
    "runtime": {"schemas"},
    "broker": {"schemas", "runtime"},
    "firmware": {"schemas", "runtime", "broker"},  # deploy writes the node's credentials file
    "zones": {"schemas", "runtime"},
    "navigation": {"schemas", "runtime", "zones"},
    "robot_agent": {"schemas", "runtime", "zones", "navigation"},  # never ROS, never the simulator
    "zone_sim": {"schemas", "runtime", "broker", "firmware"},  # runs the firmware's own logic
    "experiments": {"schemas", "runtime", "broker", "zones", "navigation", "robot_agent", "zone_sim"},
    "ros_bridge": {"schemas", "runtime", "zones", "navigation", "robot_agent"},
    "ros2_bridge": {"schemas", "runtime", "zones", "navigation", "ros_bridge"},  # feed; --robot: exit finder
    "console": {"schemas", "runtime", "broker", "zones"},  # the MQTT contract and the one zone rule
}
"""What each component may import, as docs/architecture.md's table says; the wsnav CLI may import all of them."""
COMPONENTS = list(ALLOWED)
TOP_LEVEL = set(COMPONENTS)


def python_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*.py") if "device" not in p.relative_to(REPO).parts]


def imported_names(source: Path) -> set[str]:
    """Absolute module names a file imports (also inside functions and TYPE_CHECKING blocks); for
    `from wsnav import x` the name is `wsnav.x`."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(source.read_text(), filename=str(source))):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module)
            if node.module == "wsnav":
                out.update(f"wsnav.{alias.name}" for alias in node.names)
    return out


def wsnav_component(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if parts[0] == "wsnav" and len(parts) > 1 else None


@pytest.mark.parametrize("component", COMPONENTS)
def test_a_component_imports_only_what_the_architecture_allows(component: str) -> None:
    sources = python_files(REPO / component)
    assert sources
    allowed = ALLOWED[component] | {component}
    bad = set()
    for p in sources:
        for name in imported_names(p):
            used = wsnav_component(name)
            if used is not None and used not in allowed:
                bad.add(f"{p.relative_to(REPO)} imports wsnav.{used}")
    assert not bad, sorted(bad)


def test_every_import_of_our_code_goes_through_the_wsnav_namespace() -> None:
    """A top-level `import schemas` would load a second copy of the module (or PyPI's package of that name)."""
    sources = [
        p for folder in [*COMPONENTS, "wsnav", "tests", "bench", "sites"] for p in python_files(REPO / folder)
    ]
    bad = {
        f"{p.relative_to(REPO)}: {name}"
        for p in sources
        for name in imported_names(p)
        if name.split(".")[0] in TOP_LEVEL
    }
    assert not bad, sorted(bad)


def test_the_architecture_page_states_the_allow_list() -> None:
    page = (REPO / "docs" / "architecture.md").read_text()
    for component, allowed in ALLOWED.items():
        row = next((line for line in page.splitlines() if line.startswith(f"| `{component}/`")), None)
        assert row is not None, f"docs/architecture.md has no row for {component}/"
        cell = row.rstrip(" |").rsplit("|", 1)[-1]
        stated = {name.strip(" `/") for name in cell.split(",") if name.strip(" `/-")}
        assert stated == allowed, f"{component}: page says {sorted(stated)}, code allows {sorted(allowed)}"


def test_every_component_ships_in_the_wheel_and_the_image() -> None:
    """A component missing from the namespace or the image's build context installs, then fails to import."""
    import tomllib

    include = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"][
        "include"
    ]
    assert include == ["wsnav*"], "the wheel installs one top-level name, wsnav"
    context = (REPO / ".dockerignore").read_text().splitlines()
    for component in COMPONENTS:
        link = REPO / "wsnav" / component
        assert link.is_symlink() and link.resolve() == (REPO / component).resolve(), f"wsnav/{component}"
        assert f"!{component}/" in context, f".dockerignore: {component}/ is left out of the image"
    assert "!wsnav/" in context


def module_name(path: Path) -> str:
    rel = path.relative_to(REPO).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(["wsnav", *parts] if parts[0] != "wsnav" else parts)


def test_no_module_of_ours_imports_itself_back_through_others() -> None:
    """A cycle (runner -> cluster -> runner was one) makes import order matter and hides what depends on
    what; lazy imports inside functions count too."""
    import graphlib

    modules = {module_name(p): p for folder in [*COMPONENTS, "wsnav"] for p in python_files(REPO / folder)}
    graph = {
        name: {
            dep
            for imported in imported_names(path)
            for dep in (imported, imported.rsplit(".", 1)[0])
            if dep in modules and dep != name and modules[dep].name != "__init__.py"
        }
        for name, path in modules.items()
    }
    try:
        list(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle: {' -> '.join(exc.args[1])}")


def test_commands_run_outside_the_checkout_where_only_wsnav_is_importable(tmp_path: Path) -> None:
    """From the checkout, the folders are importable by their bare names too, which hid a dynamic import of
    `console.terminal`: installed, every `wsnav status|watch|block|...` failed with ModuleNotFoundError."""
    import subprocess
    import sys

    (tmp_path / "creds.json").write_text("{}")
    proc = subprocess.run(
        [sys.executable, "-m", "wsnav.cli", "status", "--site", str(REPO / "sites" / "school"),
         "--credentials", str(tmp_path / "creds.json"), "--broker", "127.0.0.1:1"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.count("\n") == 1 and "creds.json" in proc.stderr, proc.stderr


def test_no_test_module_or_benchmark_imports_a_test_module() -> None:
    """Importing a test module runs its module-level set-up twice and ties one test file to another's internals:
    shared helpers live in the fixtures modules (tests/*_fixtures.py and the like)."""
    found = set()
    for p in [*python_files(REPO / "tests"), *python_files(REPO / "bench")]:
        for node in ast.walk(ast.parse(p.read_text(), filename=str(p))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module == "tests":
                names = [f"tests.{alias.name}" for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            found |= {f"{p.relative_to(REPO)} imports {n}" for n in names if n.startswith("tests.test_")}
    assert not found, sorted(found)
