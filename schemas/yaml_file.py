"""Reading a YAML mapping from a file with one-line errors: shared by site, scenario and agent config files."""

from __future__ import annotations

from pathlib import Path

import yaml


def read_yaml_mapping(
    path: Path, error: type[Exception], what: str, missing: str | None = None
) -> dict[str, object]:
    """The file's top-level mapping; raises `error` with one line (`path: problem`) when it cannot be had.

    `what` names the file with its article ("a site file"); `missing` replaces "no such <what>" if given.
    """
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        bare = what.split(" ", 1)[1]
        raise error(f"{path}: {missing or f'no such {bare}'}") from None
    except OSError as exc:
        raise error(f"{path}: cannot read: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(raw, dict):
        raise error(f"{path}: {what} must be a YAML mapping")
    return raw
