"""Update mode: loaded instead of the app (otaboot.py), so all of the heap is its own.

Update mode (`update`, an `ota.json` in stage `fetch`): join Wi-Fi, connect subscribed to the node's
`ota/chunk` topic, and pull the update: ask (`ota/request`, schemas.messages.OtaRequest) for the manifest (file
0, written to `ota.man` and parsed from there), check it against the `update` command's signature (HMAC-SHA256
under the node's `update_key`, read from config.json here: schemas.credentials.sign_manifest; a node without
one takes no update), then each file chunk by chunk into `<name>.tmp`, hashed as it comes and checked against
the manifest's sha256. Nothing is replaced until every file is whole and matches; then otaboot.swap renames
each old file to `<name>.bak` and the new one in (idempotent: a power cut is finished at the next boot, by
otaboot, since this file may be the one half moved), sets the stage to `trial` and resets. A FAT filesystem
(fscheck.py: the swap is not power-cut safe there), a bad signature,
manifest or file abandons the update (the old files never moved) and says why in the node's `info`; a lost
link resets the board, whose next boot retries (otaboot counts them).

Safe mode (safemode.py, when `import app` fails with nothing to roll back to) uses its `Link`; it is a module of
its own so that update mode does not carry its code.

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


class OtaAbort(Exception):
    """The update itself is bad (manifest, size, hash): no retry will fix it."""


class _Client(mqtt.MQTTClient):
    """The app's MQTT client, but a message up to a chunk's size is read into one buffer allocated with the
    client (later, a fragmented heap may have no 522 bytes in one piece) and handed over as a view of it, valid
    until the next read; the app's client hands over 128 bytes at most."""

    def __init__(self, *args) -> None:
        super().__init__(*args)
        self.buf = memoryview(bytearray(_HEADER + _CHUNK))

    def _skip(self, n: int, deadline):  # pyright: ignore[reportIncompatibleMethodOverride] (a view, read as bytes)
        if n <= 128 or n > _HEADER + _CHUNK:
            return super()._skip(n, deadline)
        buf = self.buf
        got = 0
        while got < n:
            if time.ticks_diff(deadline, time.ticks_ms()) <= 0:
                raise mqtt.MQTTError("timed out waiting for the broker")
            try:
                k = self._fed(500).readinto(buf[got:n])
            except OSError as exc:
                if exc.errno == 110 or exc.errno == 11:  # a step's silence (mqtt._recv's ETIMEDOUT, EAGAIN)
                    continue
                raise
            if k is None:
                continue
            if not k:
                raise mqtt.MQTTError("connection closed by broker")
            got += k
        return buf[:n]


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
            client.publish(
                self.request, ('{"v":1,"file":%d,"offset":%d}' % (index, offset)).encode(), False, 0
            )
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

    def get(self, index: int, size, digest: str, out, key=None) -> None:
        """The whole of file `index` (its `size`, or None for the manifest) written to `out`, checked against
        sha256 `digest`, or with `key` (64 bytes: one SHA-256 block, used as it is) against HMAC-SHA256."""
        h = sha256(bytes(b ^ 0x36 for b in key)) if key else sha256()
        offset = 0
        while True:
            n, data = self.chunk(index, offset)
            if n > (_MAX_MANIFEST if size is None else _MAX_FILE) or (size is not None and n != size):
                raise OtaAbort("size of file %d" % index)
            if offset + len(data) > n or (len(data) == 0 and offset < n):
                raise OtaAbort("bad chunk")
            h.update(data)
            out.write(data)
            offset += len(data)
            self.done += len(data)
            if offset >= n:
                break
        h = h.digest()
        if key:
            h = sha256(bytes(b ^ 0x5C for b in key) + h).digest()
        if "".join("%02x" % b for b in h) != digest:  # not binascii: a Python module on some ports
            raise OtaAbort("bad signature" if key else "sha256 of file %d" % index)

    def fetch(self, st) -> None:
        """The manifest, then each file into `<name>.tmp`; stage `swap` saved once all are whole and checked."""
        import fscheck

        if fscheck.fat():
            raise OtaAbort("FAT filesystem")
        with open(
            "config.json"
        ) as f:  # here, not in nodeconfig: one more key in the app's config dict crossed
            key = json.load(f).get("update_key")  # a dict size on the 64-bit port (a 38 KiB setup failed)
        if type(key) is not str or len(key) != 64:
            raise OtaAbort("no update key")
        key = key.encode()
        if st["stage"] == "config":  # a configuration, not an update (otaconfig.py)
            import otaconfig

            otaconfig.fetch(self, st, key)
            return
        with open("ota.man", "wb") as out:  # to the flash, and parsed from there: never whole in the heap
            self.get(0, None, st["manifest"], out, key)
        del key
        gc.collect()
        with open("ota.man") as f:
            manifest = json.load(f)
        otaboot.remove("ota.man")
        st["version"] = manifest["version"]
        files = [(f["name"], f["size"], f["sha256"]) for f in manifest["files"]]  # lighter than the dicts
        del manifest
        gc.collect()
        names = []
        if not 0 < len(files) <= _MAX_FILES:
            raise OtaAbort("manifest")
        for name, size, _sha in files:
            if (
                type(name) is not str
                or not name.endswith(".mpy")
                or "/" in name
                or name.startswith(".")
                or name == "otaboot.mpy"
                or name == "nodeconfig.mpy"  # schemas OTA_BOOT_FILES
                or type(size) is not int
            ):
                raise OtaAbort("manifest")
            names.append(name)
        st["files"] = names
        otaboot.save(st)  # the names, so that an abandoned fetch removes its .tmp files
        for name in names:
            otaboot.remove(name + ".bak")  # a stale one, of an update that never swapped
        for i, (name, size, sha) in enumerate(files):
            with open(name + ".tmp", "wb") as out:
                self.get(i + 1, size, sha, out)
            gc.collect()
            print("ota: got", name, self.done)
        st["stage"] = "swap"
        otaboot.save(st)


def update(cfg, st) -> None:
    """Update mode (otaboot.boot): fetch, swap (otaboot.swap), reset into the trial boot. Never returns."""
    link = None
    try:
        link = Fetcher(cfg)
        link.up()
        link.fetch(st)
        otaboot.swap(st, link.wdt.feed)
    except OtaAbort as exc:
        otaboot.clear(st, ".tmp")
        if link is not None:
            import safemode

            safemode.info(link, "ota: " + str(exc))
    except Exception as exc:  # the link, the flash: the next boot tries again (otaboot counts them)
        print("ota: retry,", exc)
    machine.reset()
