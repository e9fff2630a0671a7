"""`wsnav log`: the console's event log read back without a broker; a missing or broken log is one line."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from tests.site_fixtures import tiny_site
from tests.stack_fixtures import WSNAV
from wsnav.console.event_log import Event, EventLog, log_path


def run_log(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*WSNAV, "log", *args], capture_output=True, text=True, timeout=60)


def test_wsnav_log_prints_the_newest_events_and_refuses_a_missing_log_in_one_line(tmp_path: Path) -> None:
    site = tiny_site(tmp_path / "tiny")
    state = tmp_path / "state"
    missing = run_log("--site", str(site), "--state-dir", str(state))
    assert missing.returncode == 2 and missing.stderr.count("\n") == 1 and "no event log" in missing.stderr
    events = EventLog(log_path(state, "tiny"))
    events.add([Event(1000.0 + i, "block_set", f"b{i}", f"block b{i} set: zone z1") for i in range(5)])
    events.close()
    out = run_log("--site", str(site), "--state-dir", str(state), "--last", "2")
    assert out.returncode == 0, out.stderr
    assert [line.split("  ", 1)[1] for line in out.stdout.splitlines()] == [
        "block b3 set: zone z1",
        "block b4 set: zone z1",
    ]
    as_json = run_log("--site", str(site), "--state-dir", str(state), "--last", "1", "--json")
    assert json.loads(as_json.stdout) == {
        "t": 1004.0,
        "kind": "block_set",
        "subject": "b4",
        "text": "block b4 set: zone z1",
    }
    log_path(state, "tiny").write_bytes(b"not a database" * 100)
    broken = run_log("--site", str(site), "--state-dir", str(state))
    assert broken.returncode == 2 and broken.stderr.count("\n") == 1 and "not an event log" in broken.stderr
