"""Over-the-air app updates end to end: `wsnav firmware ota` (firmware/ota.py) against the project's broker
(`wsnav broker run`, with the operator's and the node's real credentials and ACL) and a node on the MicroPython
unix port (firmware/unix_board.py: the board's filesystem is a folder, boot.py and main.py run at each reset,
machine.reset() and a starved watchdog restart the process, a killed process is a power cut).

Versions are told apart by FIRMWARE_VERSION (what `info` reports); what the tests assert is which version runs
(the node's info as the broker delivers it, and the files on the board), never how long anything took.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from tests import ota_fixtures
from tests.ota_fixtures import (
    NETWORKS,
    NODE,
    QUICK,
    SITE,
    SITE_DIR,
    WAIT,
    Board,
    Infos,
    follow,
    node_key,
    update_mode_then_trial,
)
from wsnav.firmware.build import build
from wsnav.firmware.ota import OtaServer, Update, make_update
from wsnav.firmware.ota_config import ConfigServer, Settings, seal_for
from wsnav.firmware.testing import (
    SHORT_TRIAL,
    SiteBroker,
    build_for_host,
    fake_flash,
    versioned_sources,
)
from wsnav.runtime.mqtt_bus import MqttBus
from wsnav.schemas.credentials import UPDATE_KEY_FILE, Credentials, node_update_key
from wsnav.schemas.messages import OTA_BOOT_FILES

creds, broker, infos = ota_fixtures.creds, ota_fixtures.broker, ota_fixtures.infos
"""The site's credentials, `wsnav broker run` with them, the node's `info` as the operator sees it (tests/ota_fixtures.py)."""

pytestmark = pytest.mark.slow

OLD, NEW, BROKEN, LOOPING, LATE = "1.0.0-old", "1.0.0-new", "1.0.0-bad", "1.0.0-loop", "1.0.0-late"
LATE_FAILURE = """
_iteration = Node.iteration
_connected = None


def _late(self):
    global _connected
    _iteration(self)
    if self.connects and _connected is None:
        _connected = self.ticks()
    if _connected is not None and ticks_diff(self.ticks(), _connected) > 8000:
        raise RuntimeError("sensor loop failed")


Node.iteration = _late
"""
"""Appended to app.py: from 8 s after its first connect every pass of the loop fails (then the loop stops
feeding the watchdog, which resets the board)."""
APPENDED = {
    BROKEN: {"app.py": '\nraise RuntimeError("broken app")\n'},
    LOOPING: {"app.py": "\nimport machine\n\nmachine.reset()\n"},  # a reset before it ever connects
    LATE: {"app.py": LATE_FAILURE},
}


@pytest.fixture(scope="module")
def fw(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Source folders by version, their builds (`<version>-build`), and the host stubs (`stubs`)."""
    root = tmp_path_factory.mktemp("ota-fw")
    out: dict[str, Path] = {"stubs": build_for_host(root / "host")[1]}
    for version in (OLD, NEW, BROKEN, LOOPING, LATE, QUICK):
        consts = SHORT_TRIAL if version == QUICK else None
        out[version] = versioned_sources(root / f"src-{version}", version, APPENDED.get(version), consts)
        build(root / f"{version}-build", out[version])
        out[f"{version}-build"] = root / f"{version}-build"
    return out


@pytest.fixture
def board_of(
    fw: dict[str, Path], creds: Path, broker: SiteBroker, tmp_path: Path
) -> Iterator[Callable[[str], Board]]:
    made: list[Board] = []

    def make(version: str, networks: dict[str, str] | None = None) -> Board:
        b = Board(fw, version, creds, broker, tmp_path, networks)
        b.unix.power_on()
        made.append(b)
        return b

    yield make
    for b in made:
        b.unix.close()


def ota_cli(fw: dict[str, Path], creds: Path, broker: SiteBroker, version: str, timeout_s: float = WAIT):
    """`wsnav firmware ota` as an operator runs it, in the background; returns the process."""
    cmd = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "ota"),
        *("--site", str(SITE_DIR), "--broker", f"{broker.host}:{broker.port}"),
        *("--credentials", str(creds / "operator.json"), "--nodes", NODE),
        *("--source", str(fw[version]), "--timeout", str(timeout_s)),
    ]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def config_cli(creds: Path, broker: SiteBroker, stdin: str, *change: str) -> subprocess.CompletedProcess[str]:
    """`wsnav firmware config` as an operator runs it: `--wifi` (the SSID and key on stdin) unless `change` says
    what changes."""
    cmd = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "config"),
        *("--site", str(SITE_DIR), "--broker", f"{broker.host}:{broker.port}"),
        *("--credentials", str(creds / "operator.json"), "--nodes", NODE, "--timeout", str(WAIT)),
        *(change or ("--wifi",)),
    ]
    return subprocess.run(cmd, input=stdin, capture_output=True, text=True, timeout=WAIT * 2)


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=WAIT * 3)
    return proc.returncode, out, err


def serve(
    broker: SiteBroker, creds: Path, update: Update, command: bool = True, manifest: str | None = None
) -> list[str]:
    """firmware.ota.OtaServer in this process, as the operator: `update` served to NODE until it ends; with
    `command`, the `update` command sent first, carrying `manifest` (default: the manifest signed with NODE's
    key, as `wsnav firmware ota` sends it). Returns the failures."""
    from wsnav.console.operator_commands import node_command
    from wsnav.schemas.site import load_site

    op = Credentials.model_validate_json((creds / "operator.json").read_text())
    bus = MqttBus(
        broker.host, broker.port, client_id="ota-test", username=op.username, password=op.password
    ).connect(30)
    try:
        server = OtaServer(bus, SITE, update, [NODE], say=lambda _line: None)
        server.subscribe()
        if command:
            signed = manifest or update.signature(node_key(creds))
            pub = node_command(load_site(SITE_DIR), NODE, "update", manifest=signed)
            assert bus.publish_confirmed(pub.topic, pub.payload)
        return server.run(WAIT)
    finally:
        bus.close()


def test_an_update_runs_the_new_version_and_leaves_no_backup(fw, creds, broker, infos, board_of) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    code, out, err = finish(ota_cli(fw, creds, broker, NEW))
    assert code == 0, (out, err, board.serial()[-3000:])
    assert f"{NODE}: running {NEW}" in out and "(100%)" in out
    assert infos.wait(lambda i: i.fw == NEW).error is None
    board.wait_confirmed()
    kept = sorted(
        [
            "ota.ok",
            *(f"{p.name}.bak" for p in fw[f"{OLD}-build"].glob("*.mpy") if p.name not in OTA_BOOT_FILES),
        ]
    )
    assert board.leftovers() == kept, board.leftovers()  # the old version, until the next boot
    assert (board.fs / "app.mpy").read_bytes() == (fw[f"{NEW}-build"] / "app.mpy").read_bytes()
    board.power_cut()
    board.wait_serial("ota: backups removed")
    assert board.leftovers() == []


def test_a_power_cut_mid_transfer_then_the_update_completes(fw, creds, broker, infos, board_of) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    proc = ota_cli(fw, creds, broker, NEW)
    board.wait_serial("ota: got")  # some files whole in .tmp, the rest not yet
    board.power_cut()
    code, out, err = finish(proc)
    assert code == 0, (out, err, board.serial()[-3000:])
    assert "exit -9" in board.unix.resets
    infos.wait(lambda i: i.fw == NEW)
    board.wait_confirmed()
    assert board.unfinished() == []


def test_a_corrupted_file_is_refused_and_the_old_version_keeps_running(
    fw, creds, broker, infos, board_of, tmp_path: Path
) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    good = make_update(tmp_path / "build", fw[NEW])
    payloads = list(good.payloads)
    payloads[1] = payloads[1][:-1] + bytes([payloads[1][-1] ^ 1])  # one bit flipped in transit
    bad = Update(good.manifest, payloads)
    failures = serve(broker, creds, bad)
    assert failures == [f"{NODE}: update failed: ota: sha256 of file 1"]
    board.wait_serial("mqtt up")  # the old app, after the abandoned update
    assert infos.wait(lambda i: i.fw == OLD and i.uptime_s < 30 and i.error is None, WAIT)
    assert board.leftovers() == []
    assert (board.fs / "app.mpy").read_bytes() == (fw[f"{OLD}-build"] / "app.mpy").read_bytes()


@pytest.mark.parametrize("signed_with", ["nothing", "another key", "the site's key"])
def test_an_update_not_signed_with_the_nodes_key_is_refused(
    fw, creds, broker, infos, board_of, tmp_path: Path, signed_with: str
) -> None:
    """Whoever holds the operator's password can send an `update`, but the node takes only a manifest signed
    with its own key: a bare sha256, another site's key or the site's key itself (not the node's derived one)
    are refused before any file is fetched, and the old version keeps running."""
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    update = make_update(tmp_path / "build", fw[NEW])
    site_key = (creds / UPDATE_KEY_FILE).read_text().strip()
    manifest = {
        "nothing": update.digest,
        "another key": update.signature(node_update_key("0" * 64, NODE)),
        "the site's key": update.signature(site_key),
    }[signed_with]
    failures = serve(broker, creds, update, manifest=manifest)
    assert failures == [f"{NODE}: update failed: ota: bad signature"], board.serial()[-3000:]
    assert "ota: got" not in board.serial()  # not one file taken
    board.wait_serial("mqtt up")
    assert infos.wait(lambda i: i.fw == OLD and i.uptime_s < 30 and i.error is None)
    assert board.leftovers() == []
    assert (board.fs / "app.mpy").read_bytes() == (fw[f"{OLD}-build"] / "app.mpy").read_bytes()


def test_an_update_to_a_board_whose_flash_is_fat_is_refused(fw, creds, broker, infos, board_of) -> None:
    """The swap renames files over old ones, which a power cut can leave unreadable on FAT: a board whose flash
    is FAT (its `flashbdev` reads an image MicroPython's VfsFat formatted: testing.fake_flash) refuses before
    fetching anything, and `wsnav firmware ota` says why and what to do."""
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    fake_flash(board.fs, "VfsFat")
    code, out, err = finish(ota_cli(fw, creds, broker, NEW))
    assert code == 1, (out, err, board.serial()[-3000:])
    assert f"{NODE}: update failed: ota: FAT filesystem (its flash is FAT, where a power cut" in err, err
    assert "ota: got" not in board.serial()
    assert board.leftovers() == []
    assert infos.wait(lambda i: i.fw == OLD and i.error is None)
    assert (board.fs / "app.mpy").read_bytes() == (fw[f"{OLD}-build"] / "app.mpy").read_bytes()


def test_a_node_without_an_update_key_takes_no_update(
    fw, creds, broker, infos, board_of, tmp_path: Path
) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    config = json.loads((board.fs / "config.json").read_text())
    del config["update_key"]
    (board.fs / "config.json").write_text(json.dumps(config))  # as deployed before update keys existed
    failures = serve(broker, creds, make_update(tmp_path / "build", fw[NEW]))
    assert failures == [f"{NODE}: update failed: ota: no update key"]
    assert board.leftovers() == []
    assert infos.wait(lambda i: i.fw == OLD and i.error is None)


def test_ota_without_the_sites_update_key_is_one_line(fw, creds, tmp_path: Path) -> None:
    """Refused before it connects (no broker here) or sends anything."""
    op = tmp_path / "op"
    op.mkdir()
    shutil.copyfile(creds / "operator.json", op / "operator.json")  # the operator's login, not the update key
    cmd = [
        *(sys.executable, "-m", "wsnav.cli", "firmware", "ota"),
        *("--site", str(SITE_DIR), "--broker", "127.0.0.1:1"),
        *("--credentials", str(op / "operator.json"), "--nodes", NODE, "--source", str(fw[NEW])),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=WAIT)
    assert proc.returncode == 2, proc
    assert proc.stderr.strip().splitlines() == [
        f"wsnav: error: {op / UPDATE_KEY_FILE}: cannot read the site's update key (No such file or directory); "
        "wsnav broker credentials makes it"
    ], proc.stderr


def test_a_new_app_that_fails_to_import_is_rolled_back(fw, creds, broker, infos, board_of) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    code, out, err = finish(ota_cli(fw, creds, broker, BROKEN))
    assert code == 1, (out, err)
    assert f"{NODE}: came back on {OLD}, not {BROKEN}" in err
    assert "ota: rollback" in board.serial()
    assert board.leftovers() == []
    for name in ("app.mpy", "diagnostics.mpy"):
        assert (board.fs / name).read_bytes() == (fw[f"{OLD}-build"] / name).read_bytes()


def test_a_new_app_that_resets_before_it_connects_is_rolled_back_after_three_boots(
    fw, creds, broker, infos, board_of
) -> None:
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    code, out, err = finish(ota_cli(fw, creds, broker, LOOPING))
    assert code == 1, (out, err)
    assert f"{NODE}: came back on {OLD}, not {LOOPING}" in err
    assert "ota: rollback" in board.serial()
    assert board.unix.resets.count("reset") >= 5  # into update mode, into the trial, the trial boots (3)
    assert board.leftovers() == []
    assert (board.fs / "app.mpy").read_bytes() == (fw[f"{OLD}-build"] / "app.mpy").read_bytes()


def test_a_new_app_whose_loop_fails_8_s_after_connecting_is_rolled_back(
    fw, creds, broker, infos, board_of
) -> None:
    """The first connect is no confirmation: ota reports the trial, then the rollback (exit 1, naming the node
    and both versions); the board runs the old app again from its kept backups."""
    board = board_of(OLD)
    infos.wait(lambda i: i.fw == OLD)
    code, out, err = finish(ota_cli(fw, creds, broker, LATE))
    assert code == 1, (out, err, board.serial()[-3000:])
    assert f"{NODE}: running {LATE} on trial" in out, out
    assert f"{NODE}: came back on {OLD}, not {LATE}" in err, err
    assert "0 of 1 nodes" in out
    serial = board.serial()
    assert "loop error: sensor loop failed" in serial and "ota: rollback" in serial
    assert "ota: confirmed" not in serial
    assert board.unix.resets.count("watchdog") >= 3  # the trial's boots, each ended by the starved watchdog
    assert board.leftovers() == []
    for name in ("app.mpy", "diagnostics.mpy"):
        assert (board.fs / name).read_bytes() == (fw[f"{OLD}-build"] / name).read_bytes()


def test_a_version_that_keeps_failing_goes_to_safe_mode_and_takes_an_update(
    fw, creds, broker, infos, board_of
) -> None:
    """No update on trial (the failing version was put on by USB): after three watchdog resets in a row the node
    stops starting its app and waits online in safe mode, from which an update over the air is taken; the new
    version's healthy run clears the count."""
    board = board_of(LATE)
    safe = infos.wait(lambda i: (i.error or "").startswith("safe:"), WAIT * 2)
    assert safe.error == "safe: 3 resets in a row" and safe.fw == LATE
    assert board.unix.resets == ["watchdog"] * 3, board.unix.resets
    assert board.unix.wdt_fed_within(2.0)  # safe mode feeds it: no fourth reset
    code, out, err = finish(ota_cli(fw, creds, broker, NEW))
    assert code == 0, (out, err, board.serial()[-3000:])
    assert f"{NODE}: running {NEW}, confirmed" in out
    assert not (board.fs / "otaboot.loops").exists()
    assert board.unix.resets.count("watchdog") == 3


def test_a_power_cut_mid_swap_is_finished_at_the_next_boot(
    fw, creds, broker, infos, board_of, tmp_path
) -> None:
    """The three states a file can be in during the swap, built on the board's filesystem before it boots: not
    moved yet (old in place, new in .tmp), half moved (old in .bak, new in .tmp), moved (old in .bak, new in)."""
    update = make_update(tmp_path / "build", fw[NEW])
    names = [f.name for f in update.manifest.files]
    (tmp_path / "b").mkdir()
    b = Board(fw, OLD, creds, broker, tmp_path / "b")
    new_build = fw[f"{NEW}-build"]
    for k, name in enumerate(names):
        if k % 3 >= 1:
            (b.fs / name).rename(b.fs / f"{name}.bak")
        if k % 3 == 2:
            shutil.copyfile(new_build / name, b.fs / name)
        else:
            shutil.copyfile(new_build / name, b.fs / f"{name}.tmp")
    state = {"stage": "swap", "manifest": update.digest, "boots": 1, "files": names, "version": NEW}
    (b.fs / "ota.json").write_text(json.dumps(state))
    b.unix.power_on()
    try:
        infos.wait(lambda i: i.fw == NEW)
        b.wait_confirmed()
        assert b.unfinished() == []
        for name in names:
            assert (b.fs / name).read_bytes() == (new_build / name).read_bytes(), name
    finally:
        b.unix.close()


def test_safe_mode_reports_the_error_and_takes_an_update(fw, creds, broker, infos, board_of) -> None:
    board = board_of(BROKEN)
    safe = infos.wait(lambda i: (i.error or "").startswith("safe:"))
    assert safe.error == "safe: broken app"
    assert board.unix.wdt_fed_within(2.0)  # the watchdog is fed: not sitting at the REPL
    code, out, err = finish(ota_cli(fw, creds, broker, NEW))
    assert code == 0, (out, err, board.serial()[-3000:])
    infos.wait(lambda i: i.fw == NEW and i.error is None)
    board.wait_confirmed()
    assert board.unfinished() == []


def test_a_configuration_is_fetched_and_tried_on_the_boards_heap(fw, creds, broker, infos, tmp_path) -> None:
    """main.py itself at testing.HEAP from a `config` command's ota.json: update mode fetches, opens and checks
    the configuration (nodeconfig loaded there too) and swaps it in; the trial boot joins the new network and
    confirms."""
    b = Board(fw, QUICK, creds, broker, tmp_path, NETWORKS)
    sealed, signature = seal_for(
        node_key(creds), Settings(wifi=("school-new", NETWORKS["school-new"])).payload()
    )
    (b.fs / "ota.json").write_text(json.dumps({"stage": "config", "manifest": signature, "boots": 0}))
    failures: list[list[str]] = []
    server = threading.Thread(
        target=lambda: failures.append(
            follow(broker, creds, lambda bus: ConfigServer(bus, SITE, {NODE: sealed}))
        )
    )
    server.start()
    time.sleep(1)  # the server subscribed before the node asks
    node = update_mode_then_trial(b, fw["stubs"], tmp_path)
    try:
        server.join(WAIT)
        assert failures == [[]], node.output()
        b.wait_confirmed()
    finally:
        node.stop()
    assert json.loads((b.fs / "config.json").read_text())["wifi"]["ssid"] == "school-new"
    assert "MemoryError" not in node.output()


def test_update_mode_and_the_trial_boot_fit_the_boards_38_kib_heap(
    fw, creds, broker, infos, tmp_path
) -> None:
    """main.py itself on `micropython -X heapsize=HEAP` (testing.HEAP: at most the 64-bit heap leaving the board's free
    bytes after setup), from an
    `update` command's ota.json: update mode fetches and swaps, then the trial boot runs the new app."""
    update = make_update(tmp_path / "build", fw[NEW])
    b = Board(fw, OLD, creds, broker, tmp_path)
    signed = update.signature(node_key(creds))  # as the `update` command carries it
    (b.fs / "ota.json").write_text(json.dumps({"stage": "fetch", "manifest": signed, "boots": 0}))
    failures: list[list[str]] = []
    server = threading.Thread(target=lambda: failures.append(serve(broker, creds, update, command=False)))
    server.start()
    time.sleep(1)  # the server subscribed before the node asks
    node = update_mode_then_trial(b, fw["stubs"], tmp_path)
    try:
        server.join(WAIT)
        assert failures == [[]], node.output()
        assert infos.wait(lambda i: i.fw == NEW).error is None
        b.wait_confirmed()
    finally:
        node.stop()
    assert b.unfinished() == []


def test_a_new_wifi_network_sent_over_the_air_is_tried_and_kept(fw, creds, broker, infos, board_of) -> None:
    """The operator moves a node to another network with `wsnav firmware config`: the node fetches the sealed
    settings, boots with them on trial, joins the new network with its key (the fake radio refuses any other) and
    confirms; the command exits 0 and the board's config.json has the new network, everything else kept."""
    board = board_of(QUICK, NETWORKS)
    infos.wait(lambda i: i.fw == QUICK)
    before = json.loads((board.fs / "config.json").read_text())
    proc = config_cli(creds, broker, "school-new\nnew-key-5678\n")
    assert proc.returncode == 0, (proc.stdout, proc.stderr, board.serial()[-3000:])
    assert f"{NODE}: new configuration confirmed" in proc.stdout
    after = json.loads((board.fs / "config.json").read_text())
    assert after["wifi"] == {
        **before["wifi"],
        "ssid": "school-new",
        "password": "new-key-5678",
    }  # the rest kept
    assert {k: v for k, v in after.items() if k != "wifi"} == {k: v for k, v in before.items() if k != "wifi"}
    assert "new-key-5678" not in board.serial()


def test_a_wrong_wifi_key_sent_over_the_air_is_rolled_back(fw, creds, broker, infos, board_of) -> None:
    """A key the network refuses: the node cannot join with it, goes back to its old configuration after the
    trial's bound (testing.SHORT_TRIAL), comes back online with it and says so; the command exits 1 naming it."""
    board = board_of(QUICK, NETWORKS)
    infos.wait(lambda i: i.fw == QUICK)
    before = (board.fs / "config.json").read_bytes()
    proc = config_cli(creds, broker, "school-old\nwrong-key-0000\n")
    assert proc.returncode == 1, (proc.stdout, proc.stderr, board.serial()[-3000:])
    assert f"{NODE}: rolled back to its old configuration" in proc.stderr, proc.stderr
    assert "0 of 1 nodes kept the new configuration" in proc.stdout
    assert "ota: not online" in board.serial() and "ota: rollback" in board.serial()
    assert (board.fs / "config.json").read_bytes() == before
    assert not (board.fs / "config.json.bak").exists()
    assert infos.wait(lambda i: i.error == "config: rolled back").fw == QUICK


def test_a_node_moved_to_another_broker_is_followed_there(
    fw, creds, broker, infos, board_of, tmp_path
) -> None:
    """`--node-broker` naming another broker (the site's new Pi, same credentials): the node fetches its settings
    here, comes back on trial there and confirms there; the command follows it there and exits 0."""
    board = board_of(QUICK, NETWORKS)
    infos.wait(lambda i: i.fw == QUICK)
    new_pi = SiteBroker(SITE_DIR, creds, tmp_path / "new-pi-data")
    new_pi.start()
    try:
        there = Infos(new_pi, creds)
        proc = config_cli(creds, broker, "", "--node-broker", f"{new_pi.host}:{new_pi.port}")
        assert proc.returncode == 0, (proc.stdout, proc.stderr, board.serial()[-3000:])
        assert f"{NODE}: new configuration confirmed" in proc.stdout
        assert there.wait(lambda i: i.fw == QUICK and not i.trial).error is None
        there.close()
    finally:
        new_pi.kill()
    assert json.loads((board.fs / "config.json").read_text())["broker"]["port"] == new_pi.port
