"""`wsnav firmware build|deploy|flash`: from the sources in firmware/device to a node online (`wsnav firmware ota`,
which logs in as the operator, is wsnav/ota_command.py)."""

from __future__ import annotations

import argparse
import shlex
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from wsnav.firmware.board import MpremoteBoard
from wsnav.firmware.build import SIZE_TARGET, BuildError, build, compile_commands
from wsnav.firmware.deploy import (
    FLASH_BAUD,
    FLASH_MODES,
    ONLINE_S,
    Deployer,
    DeployError,
    check_config,
    check_image,
    deploy_plan,
    firmware_files,
    flash_commands,
    format_plan,
)
from wsnav.runtime.cli_support import CliError

if TYPE_CHECKING:
    from wsnav.runtime.cli_support import Parser

DEFAULT_OUT = Path("build/firmware")


def register(sub: argparse._SubParsersAction[Parser]) -> None:
    fw = sub.add_parser("firmware", help="build, deploy and flash the ESP8266 zone-node firmware")
    fw_sub = fw.add_subparsers(dest="firmware_command", required=True, parser_class=type(fw))

    b = fw_sub.add_parser("build", help="compile firmware/device to .mpy with mpy-cross and print the sizes")
    b.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"build folder (default {DEFAULT_OUT})")
    b.add_argument("--dry-run", action="store_true", help="print the mpy-cross commands, run nothing")
    b.set_defaults(func=build_command)

    d = fw_sub.add_parser(
        "deploy",
        help="update a board (running or not) with mpremote: maintenance mode, copy, verify sha256, reset",
    )
    d.add_argument("--port", required=True, help="serial port of the board, e.g. /dev/ttyUSB0")
    d.add_argument("--config", type=Path, required=True, help="the node's credentials file (its config.json)")
    d.add_argument(
        "--build", type=Path, help="an existing build folder (default: build now, into a temp folder)"
    )
    d.add_argument(
        "--keep-wifi",
        action="store_true",
        help="allow a config without wifi.ssid: the board keeps the network it joined before",
    )
    d.add_argument(
        "--wait-online",
        type=float,
        default=ONLINE_S,
        metavar="S",
        help=f"after the reset, read the board's console until the node reaches its broker (default {ONLINE_S:.0f} "
        "s; 0: do not wait, e.g. on a workbench away from the site's network)",
    )
    d.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    d.set_defaults(func=deploy_command)

    f = fw_sub.add_parser("flash", help="erase the ESP8266 and write a MicroPython image with esptool")
    f.add_argument("--port", required=True, help="serial port of the board, e.g. /dev/ttyUSB0")
    f.add_argument("--image", type=Path, required=True, help="ESP8266_GENERIC-*.bin from micropython.org")
    f.add_argument("--baud", type=int, default=FLASH_BAUD, help=f"write speed (default {FLASH_BAUD})")
    f.add_argument(
        "--flash-mode",
        choices=FLASH_MODES,
        default="keep",
        help="SPI flash mode written into the image (default keep; dout when a board boots garbage)",
    )
    f.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    f.set_defaults(func=flash_command)


def _print(cmd: list[str]) -> None:
    print(shlex.join(cmd))


def _run(cmds: list[list[str]]) -> None:
    for cmd in cmds:
        _print(cmd)
        try:
            proc = subprocess.run(cmd, check=False)
        except OSError as exc:
            raise CliError(f"cannot run {cmd[0]}: {exc.strerror}") from None
        if proc.returncode != 0:
            raise CliError(f"{Path(cmd[0]).name} failed (exit {proc.returncode}): {shlex.join(cmd[1:4])} ...")


def _build(out: Path) -> None:
    try:
        built = build(out)
    except BuildError as exc:
        raise CliError(str(exc)) from None
    total = 0
    for item in built:
        total += item.size
        print(f"{item.size:7d}  {item.path}")
    verdict = "ok" if total <= SIZE_TARGET else "OVER TARGET"
    print(f"{total:7d}  total ({verdict}: target {SIZE_TARGET // 1024} KiB)")


def build_command(args: argparse.Namespace) -> int:
    if args.dry_run:
        try:
            cmds = compile_commands(args.out)
        except BuildError as exc:
            raise CliError(str(exc)) from None
        for cmd in cmds:
            _print(cmd)
        return 0
    _build(args.out)
    return 0


def deploy_command(args: argparse.Namespace) -> int:
    try:
        cfg = check_config(args.config, keep_wifi=args.keep_wifi)
    except DeployError as exc:
        raise CliError(str(exc)) from None
    if args.build is not None and not args.dry_run and not (args.build / "app.mpy").is_file():
        raise CliError(f"{args.build}: not a firmware build folder (run `wsnav firmware build` first)")
    print(f"node {cfg.node} (zone {cfg.zone}, site {cfg.site}) -> broker {cfg.broker.host}:{cfg.broker.port}")
    if args.dry_run:
        out = args.build or DEFAULT_OUT
        if args.build is None:
            for cmd in compile_commands(out):
                _print(cmd)
        for line in format_plan(deploy_plan(args.port, firmware_files(out, args.config))):
            print(line)
        return 0
    with tempfile.TemporaryDirectory(prefix="wsnav-fw-") as tmp:
        out = args.build
        if out is None:
            out = Path(tmp)
            _build(out)
        deployer = Deployer(MpremoteBoard(args.port))
        try:
            copied = deployer.deploy(firmware_files(out, args.config))
        except DeployError as exc:
            raise CliError(str(exc)) from None
    print(f"deployed: {len(copied)} files changed, all verified; the board is restarting")
    if args.wait_online > 0:
        try:
            took = deployer.wait_online(args.wait_online)
        except DeployError as exc:
            raise CliError(str(exc)) from None
        print(
            f"node {cfg.node} is online: it reached {cfg.broker.host}:{cfg.broker.port} {took:.1f} s after the reset"
        )
    return 0


def flash_command(args: argparse.Namespace) -> int:
    try:
        check_image(args.image)
    except DeployError as exc:
        raise CliError(str(exc)) from None
    if not 9600 <= args.baud <= 2_000_000:
        raise CliError(f"--baud {args.baud} is out of range (9600..2000000)")
    cmds = flash_commands(args.port, args.image, args.baud, args.flash_mode)
    if args.dry_run:
        for cmd in cmds:
            _print(cmd)
        return 0
    _run(cmds)
    return 0
