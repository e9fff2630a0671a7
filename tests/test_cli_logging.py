"""Logging is set up once, by the command: every wsnav command takes --log-level, and a component's records
come out on stderr as one line each, at the level chosen."""

from __future__ import annotations

import subprocess
import sys

from wsnav.cli import build_parser, leaf_parsers


def test_every_command_takes_log_level() -> None:
    leaves = leaf_parsers(build_parser())
    assert len(leaves) > 20
    missing = [p.prog for p in leaves if not any("--log-level" in a.option_strings for a in p._actions)]
    assert not missing, missing


def test_a_components_records_come_out_at_the_level_chosen() -> None:
    """A component only names its logger; the command decides what is printed (debug here, none by default)."""
    code = (
        "import logging, sys; from wsnav.cli import main; "
        "import wsnav.cli as c; "
        "c.REGISTRARS.append(lambda sub: sub.add_parser('probe').set_defaults("
        "func=lambda a: logging.getLogger('wsnav.zones.probe').debug('seen at debug') or 0)); "
        "sys.exit(main(sys.argv[1:]))"
    )
    quiet = subprocess.run([sys.executable, "-c", code, "probe"], capture_output=True, text=True, timeout=60)
    loud = subprocess.run(
        [sys.executable, "-c", code, "probe", "--log-level", "debug"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert (quiet.returncode, quiet.stderr) == (0, "")
    assert loud.returncode == 0
    lines = loud.stderr.splitlines()
    assert len(lines) == 1 and lines[0].endswith("DEBUG wsnav.zones.probe: seen at debug"), loud.stderr
