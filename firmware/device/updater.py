"""Update mode and safe mode: loaded instead of the app (otaboot.py), so all of the heap is theirs.

Update mode (`update`, an `ota.json` in stage `fetch` or `swap`): join Wi-Fi, connect subscribed to the node's
`ota/chunk` topic, and pull the update: ask (`ota/request`, schemas.messages.OtaRequest) for the manifest (file
0), check its sha256 against the `update` command's, then each file chunk by chunk into `<name>.tmp`, hashed as
it comes. Nothing is replaced until every file is whole and matches; then `swap` renames each old file to
`<name>.bak` and the new one in (idempotent: a power cut is finished at the next boot), sets the stage to `trial`
and resets. A bad manifest or file abandons the update (the old files never moved) and says why in the node's
`info`; a lost link resets the board, whose next boot retries (otaboot counts them).

Safe mode (`safe`, when `import app` fails with nothing to roll back to): connected, watchdog fed, the error in
`info`, waiting for an `update` (or `restart`) command, and a reset after SAFE_MS to try the app again.

Every wait feeds the watchdog; every socket step is bounded by the MQTT client's.
"""

import gc
import json
import os
import struct
import time

import machine
import mqtt
import otaboot
from hashlib import sha256
from micropython import const

_CHUNK = const(512)
_HEADER = const(10)
"""schemas.messages.OTA_CHUNK_HEADER: >HII, file index, offset, file size."""
_MAX_FILE = const(32768)
_MAX_MANIFEST = const(3072)
_MAX_FILES = const(24)
_CHUNK_WAIT_MS = const(4000)
_TRIES = const(5)
"""A chunk is asked for again after _CHUNK_WAIT_MS without an answer, at most _TRIES times, then the link is
taken for lost (a reset, a retry at the next boot)."""
_JOIN_MS = const(30000)
_CONNECT_MS = const(60000)
SAFE_MS = 600000


class OtaAbort(Exception):
    """The update itself is bad (manifest, size, hash): no retry will fix it."""


class _Who:
    """What diagnostics.info reads of a NodeLogic, for a node whose app is not loaded."""

    def __init__(self, cfg, base: str) -> None:
        self.node = cfg["node"]
        self.heartbeat_ms = cfg["heartbeat_ms"]
        self.status_topic = base + "status"


class _Client(mqtt.MQTTClient):
    """The app's MQTT client, but a message up to a chunk's size is read whole (the app's reads 128 bytes)."""

    def _skip(self, n: int, deadline) -> bytes:
        return self._recv(n, deadline) if n <= _HEADER + _CHUNK else super()._skip(n, deadline)


class Link:
    """Wi-Fi and one MQTT connection subscribed to `topic`, the watchdog fed in every wait."""

    def __init__(self, cfg, topic: str) -> None:
        self.wdt = machine.WDT()
        self.cfg = cfg
        self.base = "wsn/" + cfg["site"] + "/nodes/" + cfg["node"] + "/"
        self.client = _Client(
            cfg["node"],
            cfg["broker_host"],
            cfg["broker_port"],
            cfg["username"],
            cfg["password"],
            cfg["keepalive_s"],
            5000,
            self.wdt.feed,
        )
        self.topic = self.base + topic
        self.started = time.ticks_ms()

    def sleep(self, ms: int) -> None:
        """Wait `ms`, fed every 100 ms."""
        while ms > 0:
            self.wdt.feed()
            time.sleep_ms(100 if ms > 100 else ms)
            ms -= 100

    def up(self) -> None:
        """Join Wi-Fi and connect, retrying each within its own bound; OSError if either cannot be had."""
        import wifi

        w = wifi.Wifi(self.cfg["wifi_ssid"], self.cfg["wifi_password"])
        w.start()
        t0 = time.ticks_ms()
        while not w.connected():
            if time.ticks_diff(time.ticks_ms(), t0) > _JOIN_MS:
                raise OSError("wifi")
            self.sleep(100)
        t0 = time.ticks_ms()
        while True:
            try:
                self.client.connect(None, self.topic)
                return
            except OSError as exc:
                if time.ticks_diff(time.ticks_ms(), t0) > _CONNECT_MS:
                    raise
                print("ota: broker", exc)
                self.sleep(1000)

    def info(self, error: str) -> None:
        """`nodes/<node>/info` saying `error` (schemas.messages.NodeInfo, by diagnostics.info when it loads)."""
        cfg = self.cfg
        up = time.ticks_diff(time.ticks_ms(), self.started) // 1000
        try:
            import diagnostics

            topic, payload, _r, _q = diagnostics.info(
                _Who(cfg, self.base), up, 1, machine.reset_cause(), None, None, error, 0
            )
        except Exception:  # the app's own diagnostics are broken too: the fields every NodeInfo has
            topic = self.base + "info"
            payload = '{"v":1,"node":"%s","fw":"unknown","reset":"unknown","uptime_s":%d,"reconnects":0}' % (
                cfg["node"],
                up,
            )
        try:
            self.client.publish(topic, payload.encode(), True, 1)
        except OSError:
            pass
        print("info:", error)


class Fetcher(Link):
    """The update mode's transfer: chunks asked for one at a time, each answer checked against the question."""

    def __init__(self, cfg) -> None:
        super().__init__(cfg, "ota/chunk")
        self.request = self.base + "ota/request"
        self.done = 0

    def chunk(self, index: int, offset: int):
        """(file size, data) of file `index` at `offset`."""
        client = self.client
        for _ in range(_TRIES):
            client.publish(self.request, ('{"v":1,"file":%d,"offset":%d}' % (index, offset)).encode(), False, 0)
            t0 = time.ticks_ms()
            while time.ticks_diff(time.ticks_ms(), t0) < _CHUNK_WAIT_MS:
                body = client.poll()
                if body is None:
                    client.maintain()
                    self.sleep(5)
                elif len(body) >= _HEADER:
                    i, o, size = struct.unpack_from(">HII", body)
                    if i == index and o == offset:  # else an answer to an earlier question: dropped
                        return size, memoryview(body)[_HEADER:]
        raise OSError("no chunk")

    def get(self, index: int, size, digest: str, out):
        """The whole of file `index` (its `size`, or None for the manifest) written to `out` (or returned, for
        the manifest), checked against sha256 `digest`."""
        h = sha256()
        got = b""
        offset = 0
        while True:
            n, data = self.chunk(index, offset)
            if n > (_MAX_MANIFEST if size is None else _MAX_FILE) or (size is not None and n != size):
                raise OtaAbort("size of file %d" % index)
            if offset + len(data) > n or (not data and offset < n):
                raise OtaAbort("bad chunk")
            h.update(data)
            if out is None:
                got += data
            else:
                out.write(data)
            offset += len(data)
            self.done += len(data)
            if offset >= n:
                break
        if "".join("%02x" % b for b in h.digest()) != digest:  # not binascii: a Python module on some ports
            raise OtaAbort("sha256 of file %d" % index)
        return got

    def fetch(self, st) -> None:
        """The manifest, then each file into `<name>.tmp`; stage `swap` saved once all are whole and checked."""
        manifest = json.loads(self.get(0, None, st["manifest"], None))
        files = manifest["files"]
        names = []
        if not 0 < len(files) <= _MAX_FILES:
            raise OtaAbort("manifest")
        for f in files:
            name = f["name"]
            if (
                type(name) is not str
                or not name.endswith(".mpy")
                or "/" in name
                or name.startswith(".")
                or name == "otaboot.mpy"
                or type(f["size"]) is not int
            ):
                raise OtaAbort("manifest")
            names.append(name)
        st["files"] = names
        st["version"] = manifest["version"]
        otaboot.save(st)  # the names, so that an abandoned fetch removes its .tmp files
        for name in names:
            otaboot.remove(name + ".bak")  # a stale one, of an update that never swapped
        for i, f in enumerate(files):
            with open(f["name"] + ".tmp", "wb") as out:
                self.get(i + 1, f["size"], f["sha256"], out)
            gc.collect()
            print("ota: got", f["name"], self.done)
        st["stage"] = "swap"
        otaboot.save(st)


def swap(st, feed=None) -> None:
    """Each `<name>.tmp` in, its old file kept as `<name>.bak`; safe to run again from any point. `feed`: the
    watchdog's, once a file (two renames on the flash)."""
    for name in st["files"]:
        if feed is not None:
            feed()
        tmp = name + ".tmp"
        if otaboot.exists(tmp):
            if otaboot.exists(name):
                if otaboot.exists(name + ".bak"):
                    os.remove(name)
                else:
                    os.rename(name, name + ".bak")
            os.rename(tmp, name)
    st["stage"] = "trial"
    st["boots"] = 0
    otaboot.save(st)
    print("ota: swapped", st.get("version"))


def update(cfg, st) -> None:
    """Update mode (otaboot.boot): fetch if not done, swap, reset into the trial boot. Never returns."""
    link = None
    try:
        if st.get("stage") == "fetch":
            link = Fetcher(cfg)
            link.up()
            link.fetch(st)
        swap(st, link.wdt.feed if link is not None else None)
    except OtaAbort as exc:
        otaboot.clear(st, ".tmp")
        if link is not None:
            link.info("ota: " + str(exc))
    except Exception as exc:  # the link, the flash: the next boot tries again (otaboot counts them)
        print("ota: retry,", exc)
    machine.reset()


def safe(cfg, why: str) -> None:
    """Safe mode (otaboot.failed): say `why` in `info`, then wait up to SAFE_MS for a command: `update` starts
    one, `restart` resets. Never returns."""
    if not cfg:  # the app's setup had cleared it
        import nodeconfig

        cfg = nodeconfig.load("config.json")
    gc.collect()
    link = Link(cfg, "command")
    try:
        link.up()
        link.info(why)
        client = link.client
        while time.ticks_diff(time.ticks_ms(), link.started) < SAFE_MS:
            body = client.poll()
            if body is None:
                client.maintain()
                link.sleep(50)
                continue
            try:
                d = json.loads(body)
                cmd = d["command"]
                digest = d.get("manifest")
                if cmd == "update" and type(digest) is str and len(digest) == 64:
                    otaboot.save({"stage": "fetch", "manifest": digest, "boots": 0})
                    break
                if cmd == "restart":
                    break
            except Exception:  # no single message stops safe mode
                print("bad command")
    except Exception as exc:
        print("safe:", exc)
        link.sleep(1000)
    machine.reset()
