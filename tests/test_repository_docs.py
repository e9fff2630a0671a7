"""The repository explains itself: nothing refers to a design document outside it, and every test that
docs/architecture.md names as pinning a fact exists (a renamed test must take the page with it)."""

from __future__ import annotations

import re
import subprocess

from tests.conftest import REPO

OUTSIDE_DOC = "DESIGN" + ".md"  # spelled apart so this file does not match itself


def tracked_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    return [name for name in out.decode().split("\0") if name]


def test_no_tracked_file_refers_to_a_design_document_outside_the_repository() -> None:
    files = tracked_files()
    assert "README.md" in files, "git ls-files lists the repository"
    citing = []
    for name in files:
        path = REPO / name
        if not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # images, maps
        if OUTSIDE_DOC in text:
            citing.append(name)
    assert citing == [], f"these files cite a document the repository does not hold: {citing}"


DESIGN_PAGES = ("architecture.md", "dependencies.md")


def design_text() -> str:
    return "\n".join((REPO / "docs" / name).read_text(encoding="utf-8") for name in DESIGN_PAGES)


def test_every_test_the_design_pages_name_exists() -> None:
    page = design_text()
    paths = set(re.findall(r"tests/test_\w+\.py", page))
    assert len(paths) >= 8, "the pages name the tests that pin their facts"
    missing_files = sorted(p for p in paths if not (REPO / p).is_file())
    assert missing_files == []
    defined = {
        m for p in (REPO / "tests").glob("test_*.py") for m in re.findall(r"def (test_\w+)", p.read_text())
    }
    named = set(re.findall(r"\b(test_\w+)\b", page)) - {
        p.removeprefix("tests/").removesuffix(".py") for p in paths
    }
    assert len(named) >= 10
    assert sorted(named - defined) == [], "renamed or removed tests are still cited by the design pages"


def test_every_module_the_design_pages_name_exists() -> None:
    """A page that sends a newcomer to a moved file is wrong: each `folder/module.py` it names is there."""
    page = design_text()
    named = set(re.findall(r"`((?:[a-z_]+/)+[a-z_0-9]+\.py)`", page))
    assert len(named) >= 20
    assert sorted(p for p in named if not (REPO / p).is_file()) == []


def test_the_architecture_page_says_where_every_command_lives() -> None:
    from wsnav.cli import build_parser, leaf_parsers

    page = (REPO / "docs" / "architecture.md").read_text(encoding="utf-8")
    table = page[page.index("### Where each command's work lives") :]
    table = table[: table.index("\n\n", table.index("| command"))]
    missing = [p.prog for p in leaf_parsers(build_parser()) if p.prog.split()[-1] not in table]
    assert missing == []


def test_every_test_the_slow_list_names_exists() -> None:
    """A renamed slow test dropped from the list would slip into `make test-fast` unnoticed."""
    from tests.conftest import SLOW_MODULES, SLOW_TESTS

    defined = {
        f"{p.name}::{m}"
        for p in (REPO / "tests").glob("test_*.py")
        for m in re.findall(r"def (test_\w+)", p.read_text())
    }
    assert sorted(SLOW_TESTS - defined) == []
    assert sorted(m for m in SLOW_MODULES if not (REPO / "tests" / m).is_file()) == []
