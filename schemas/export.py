"""Export the JSON Schema of every message and of the site file to schemas/json/ (firmware and other
languages follow these files). Run: python -m wsnav.schemas.export [--check]."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from wsnav.schemas.credentials import Credentials, NodeConfig
from wsnav.schemas.messages import MESSAGE_MODELS
from wsnav.schemas.site_file import SiteFile

JSON_DIR = Path(__file__).parent / "json"


def rendered() -> dict[str, str]:
    """File name -> exact file text, for every exported schema."""
    models = {**MESSAGE_MODELS, "site_file": SiteFile, "credentials": Credentials, "node_config": NodeConfig}
    out: dict[str, str] = {}
    for name, model in sorted(models.items()):
        schema = model.model_json_schema(by_alias=True)
        schema["$id"] = f"https://wsnav.invalid/schemas/{name}.json"
        out[f"{name}.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def stale_files(directory: Path = JSON_DIR) -> list[str]:
    """Names of schema files that are missing, different or extra in `directory`."""
    want = rendered()
    have = {p.name for p in directory.glob("*.json")}
    return sorted(
        [n for n, text in want.items() if not (directory / n).exists() or (directory / n).read_text() != text]
        + [n for n in have - want.keys()]
    )


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if "--check" in args:
        stale = stale_files()
        if stale:
            print(f"schemas/json is out of date ({', '.join(stale)}): run 'make schemas'", file=sys.stderr)
            return 1
        return 0
    JSON_DIR.mkdir(exist_ok=True)
    for old in JSON_DIR.glob("*.json"):
        old.unlink()
    for name, text in rendered().items():
        (JSON_DIR / name).write_text(text)
        print(f"wrote {JSON_DIR / name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
