"""`wsnav firmware build|deploy|flash`: sizes, exact dry-run commands, one-line errors."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from wsnav.firmware.build import SIZE_TARGET
from wsnav.firmware.deploy import module_names


def wsnav(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wsnav.cli", "firmware", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=300,
    )


def one_line_error(proc: subprocess.CompletedProcess[str], text: str) -> None:
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and text in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


def node_config(tmp_path: Path, **changes: Any) -> Path:
    data: dict[str, Any] = {
        "username": "n1",
        "password": "p" * 24,
        "role": "node",
        "site": "school",
        "broker": {"host": "192.168.4.2", "port": 1883},
        "node": "n1",
        "zone": "z1",
        "sensor": {"type": "pir", "pin": 5},
        "heartbeat_s": 5,
        "on_delay_ms": 500,
        "off_delay_ms": 3000,
        "wifi": {"ssid": "site", "password": "wifi-secret"},
    }
    data.update(changes)
    path = tmp_path / "n1.json"
    path.write_text(json.dumps(data))
    return path


def test_build_prints_sizes_under_target(tmp_path: Path) -> None:
    out = tmp_path / "build"
    proc = wsnav("build", "--out", out)
    assert proc.returncode == 0, proc.stderr
    names = {p.name for p in out.iterdir()}
    assert names == {n + ".mpy" for n in module_names()} | {"main.py", "boot.py"}
    total = sum(p.stat().st_size for p in out.iterdir())
    assert total <= SIZE_TARGET
    assert f"{total:7d}  total (ok" in proc.stdout
    for p in out.glob("*.mpy"):
        # Version 6, no native architecture, so no sub-version: MicroPython >= 1.19 loads it (the guide's claim).
        assert p.read_bytes()[:3] == b"M\x06\x00"


def test_build_dry_run_prints_mpy_cross_commands(tmp_path: Path) -> None:
    proc = wsnav("build", "--out", tmp_path, "--dry-run")
    assert proc.returncode == 0
    cmds = [shlex.split(line) for line in proc.stdout.splitlines()]
    assert [Path(c[0]).name for c in cmds] == ["mpy-cross"] * len(module_names())
    assert not list(tmp_path.iterdir())


def test_deploy_dry_run_prints_the_mpremote_commands(tmp_path: Path) -> None:
    cfg = node_config(tmp_path)
    build = tmp_path / "b"
    proc = wsnav("deploy", "--port", "/dev/ttyUSB0", "--config", cfg, "--build", build, "--dry-run")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == "node n1 (zone z1, site school) -> broker 192.168.4.2:1883"
    cmds = [shlex.split(line) for line in lines[1:]]
    # Every session resumes: no soft reset, which would free the maintenance timer's callback.
    assert all(
        Path(c[0]).name == "mpremote" and c[1:4] == ["connect", "/dev/ttyUSB0", "resume"] for c in cmds
    )
    assert cmds[0][4:] == ["exec", "<firmware/device/maintenance.py>"]
    assert cmds[1][4] == "exec" and "_wsnav_rm(" in cmds[1][5] and "'app.py'" in cmds[1][5]
    copies = [c for c in cmds if c[4:6] == ["fs", "cp"]]
    board_names = {n + ".mpy" for n in module_names()} | {"main.py", "boot.py", "config.json"}
    assert {c[-1] for c in copies} == {f":{n}.tmp" for n in board_names}  # under temporary names
    assert [c[-2] for c in copies if c[-1] == ":config.json.tmp"] == [str(cfg)]
    renames = [c[5] for c in cmds if "os.rename" in c[-1]]
    assert len(renames) == len(board_names)
    assert "_wsnav_sha(" in cmds[-2][5] and cmds[-1][4:] == ["reset"]
    assert not build.exists()


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"broker": {"host": "", "port": 1883}}, "broker.host is empty"),
        ({"sensor": {"type": "pir"}}, "sensor.pir.pin: Field required"),
        ({"password": "short"}, "password"),
        ({"wifi": {"ssid": "", "password": ""}}, "wifi.ssid is empty"),
    ],
)
def test_deploy_refuses_bad_configs(tmp_path: Path, changes: dict[str, Any], message: str) -> None:
    cfg = node_config(tmp_path, **changes)
    one_line_error(wsnav("deploy", "--port", "/dev/ttyUSB0", "--config", cfg, "--dry-run"), message)


def test_deploy_missing_config_and_bad_build(tmp_path: Path) -> None:
    one_line_error(
        wsnav("deploy", "--port", "p", "--config", tmp_path / "nope.json", "--dry-run"), "cannot read config"
    )
    cfg = node_config(tmp_path)
    one_line_error(
        wsnav("deploy", "--port", "p", "--config", cfg, "--build", tmp_path), "not a firmware build folder"
    )


def test_flash_dry_run_prints_esptool_commands(tmp_path: Path) -> None:
    image = tmp_path / "ESP8266_GENERIC-v1.27.0.bin"
    image.write_bytes(esp_image(0x40100004))
    proc = wsnav("flash", "--port", "/dev/ttyUSB0", "--image", image, "--dry-run")
    assert proc.returncode == 0, proc.stderr
    cmds = [shlex.split(line) for line in proc.stdout.splitlines()]
    assert [Path(c[0]).name for c in cmds] == ["esptool", "esptool"]
    assert cmds[0][1:] == ["--chip", "esp8266", "--port", "/dev/ttyUSB0", "erase-flash"]
    assert cmds[1][1:] == [
        "--chip",
        "esp8266",
        "--port",
        "/dev/ttyUSB0",
        "--baud",
        "460800",
        "write-flash",
        "--flash-size=detect",
        "0",
        str(image),
    ]
    dout = wsnav("flash", "--port", "/dev/ttyUSB0", "--image", image, "--flash-mode", "dout", "--dry-run")
    assert shlex.split(dout.stdout.splitlines()[1])[-3:] == ["--flash-mode=dout", "0", str(image)]


def esp_image(entry: int) -> bytes:
    """A firmware image's header as esptool writes it (magic, segments, flash mode and size, entry point)."""
    return b"\xe9\x03\x02\x40" + entry.to_bytes(4, "little") + bytes(600 * 1024)


def test_flash_refuses_bad_images_and_args(tmp_path: Path) -> None:
    one_line_error(
        wsnav("flash", "--port", "p", "--image", tmp_path / "x.bin", "--dry-run"), "no such firmware"
    )
    small = tmp_path / "small.bin"
    small.write_bytes(b"\xe9" * 100)
    one_line_error(wsnav("flash", "--port", "p", "--image", small, "--dry-run"), "is not an ESP8266")
    text = tmp_path / "readme.bin"
    text.write_bytes(b"#" * 100_000)
    one_line_error(wsnav("flash", "--port", "p", "--image", text, "--dry-run"), "first byte")
    esp32 = tmp_path / "ESP32_GENERIC-v1.27.0.bin"
    esp32.write_bytes(esp_image(0x40081000))
    one_line_error(wsnav("flash", "--port", "p", "--image", esp32, "--dry-run"), "an ESP32 image's")
    one_line_error(wsnav("flash", "--image", text), "--port")


def test_deploy_takes_a_config_without_wifi_only_when_told_to_keep_the_boards_network(tmp_path: Path) -> None:
    cfg = node_config(tmp_path, wifi={"ssid": "", "password": ""})
    one_line_error(wsnav("deploy", "--port", "p", "--config", cfg, "--dry-run"), "--keep-wifi")
    kept = wsnav("deploy", "--port", "p", "--config", cfg, "--keep-wifi", "--dry-run")
    assert kept.returncode == 0, kept.stderr


def test_ota_refuses_bad_arguments_in_one_line(tmp_path: Path) -> None:
    site = Path(__file__).resolve().parent.parent / "sites" / "school"
    common = ("--site", site, "--broker", "127.0.0.1:1", "--credentials", tmp_path / "operator.json")
    one_line_error(wsnav("ota", *common, "--nodes", ","), "give node ids")
    one_line_error(wsnav("ota", *common, "--nodes", "n1,n1"), "each once")
    one_line_error(wsnav("ota", *common, "--nodes", "n1", "--timeout", "0"), "--timeout 0")
    source = tmp_path / "src"
    source.mkdir()
    (source / "diagnostics.py").write_text("INFO_PERIOD_MS = 1\n")
    one_line_error(wsnav("ota", *common, "--nodes", "n1", "--source", source), "no FIRMWARE_VERSION line")
    (source / "diagnostics.py").write_text('FIRMWARE_VERSION = "1.0"\n')
    one_line_error(wsnav("ota", *common, "--nodes", "n1", "--source", source), "not the firmware's sources")
    (tmp_path / "update.key").write_text("the operator's password\n")  # beside --credentials: the default
    one_line_error(wsnav("ota", *common, "--nodes", "n1"), "update.key: not an update key (64 hex digits)")


def test_config_refuses_bad_settings_in_one_line(tmp_path: Path) -> None:
    """Refused before it connects (no broker here): nothing to change, no SSID on stdin, a key WPA2 refuses, a
    bad broker address, a Mosquitto folder without a new password, a new password away from the broker's
    credentials folder."""
    site = Path(__file__).resolve().parent.parent / "sites" / "school"
    common = (
        "config",
        "--site",
        site,
        "--broker",
        "127.0.0.1:1",
        "--credentials",
        tmp_path / "operator.json",
    )

    def config(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "wsnav.cli", "firmware", *map(str, common), *args]
        return subprocess.run(cmd, input=stdin, capture_output=True, text=True, timeout=300)

    one_line_error(config("--nodes", "n1"), "nothing to change")
    one_line_error(config("--nodes", "n1", "--wifi"), "SSID on the first line")
    one_line_error(config("--nodes", "n1", "--wifi", stdin="net\nshort\n"), "Wi-Fi key: 8 to 63")
    one_line_error(config("--nodes", "n1", "--node-broker", "pi:0"), "expected HOST:PORT")
    one_line_error(config("--nodes", "n1,n1", "--wifi", stdin="net\nlong-enough\n"), "each once")
    one_line_error(
        config("--nodes", "n1", "--wifi", stdin="net\nlong-enough\n"), "cannot read the site's update key"
    )
    one_line_error(config("--nodes", "n1", "--mosquitto-config", str(tmp_path)), "goes with --new-password")
    one_line_error(config("--nodes", "n1", "--new-password"), "where the broker's credentials folder is")
