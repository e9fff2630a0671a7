"""A configuration over the air, in update mode (updater.Fetcher.fetch, for an `ota.json` in stage `config`: a
`config` command, sent by `wsnav firmware config`): loaded only there, on update mode's heap.

The configuration is fetched as an update's manifest is (file 0, written to `config.new`, its HMAC-SHA256 under
the node's update key checked against the command's), then opened: a 16-byte nonce, then JSON XORed with SHA-256
in counter mode under the same key (schemas.credentials.seal_config: the Wi-Fi key never crosses the bus in
clear). Only `wifi`, `broker` (each with its two keys of the right types, a non-empty SSID or host) and
`password` (the MQTT password, 16 characters or more: `wsnav firmware config --new-password`) may change
(schemas.credentials.CONFIG_KEYS), and its number `seq` must be above the last one taken (SEQ): checked here, not by nodeconfig, whose code does not fit beside update mode's link on the board's heap. It becomes `config.json.tmp`, the one file of an update: otaboot.swap keeps the old one as
`config.json.bak` and the next boot tries the new one (otaboot's trial), rolled back if the node is not online
with it in time (health.py). Anything wrong: OtaAbort("config"), the old config untouched.
"""

import json
import os
from hashlib import sha256

import otaboot

SEQ = "config.seq"
"""The last configuration's number (`seq`, schemas.credentials.config_seq): kept across rollbacks and updates, so
neither an older configuration nor the same one again is taken (a captured one cannot be replayed)."""


def fetch(link, st, key) -> None:
    """Fetch, check, open and merge the configuration; stage `swap` saved with `config.json` as its one file."""
    from updater import OtaAbort

    with open("config.new", "wb") as out:
        link.get(0, None, st["manifest"], out, key)
    with open("config.new", "rb") as f:
        sealed = f.read()
    otaboot.remove("config.new")
    body = bytearray(sealed[16:])
    block = b""
    for i in range(len(body)):
        if i % 32 == 0:
            block = sha256(key + b"wsnav-config" + sealed[:16] + bytes([i // 32])).digest()
        body[i] ^= block[i % 32]
    try:
        new = json.loads(body)  # pyright: ignore[reportArgumentType] (MicroPython reads a bytearray; no copy)
        del body
        seq = new.pop("seq")  # every configuration has its number: refused without one
        if type(seq) is not int or seq <= last_seq():
            raise OtaAbort("old config")  # a replay, or one older than the last taken
        stage(new, st)
    except (ValueError, TypeError, KeyError):
        raise OtaAbort("config")
    with open("config.sqt", "w") as f:  # after the state: a cut before leaves the number, not the config, behind
        f.write(str(seq))
    os.rename("config.sqt", SEQ)


def stage(new, st) -> None:
    """`new` (`wifi`, `broker` and/or `password`, each checked) merged into config.json as `config.json.tmp`, the one file of
    an update in stage `swap` saved in `st`: the next boot swaps it in and tries it. ValueError, TypeError or
    KeyError before anything is written when `new` is wrong. Also the fallback access point's (fallback_ap.py)."""
    for name in new:
        v = new[name]
        if name == "wifi":
            v = v["ssid"], v["password"]
        elif name == "broker":
            v = v["host"], v["port"]
        elif name == "password":  # the MQTT password, as long as the site's credentials' at least
            if type(v) is not str or len(v) < 16:
                raise ValueError
            continue
        else:
            raise ValueError
        if type(v[0]) is not str or not v[0] or type(v[1]) is not (str if name == "wifi" else int):
            raise ValueError
    with open("config.json") as f:
        d = json.load(f)
    for name in new:  # key by key: what else config.json has there (wifi.fallback_ap_s) stays
        if type(d.get(name)) is dict:
            d[name].update(new[name])
        else:
            d[name] = new[name]
    with open("config.json.tmp", "w") as f:
        json.dump(d, f)
    if "wifi" in new:  # into the radio's flash too: the trial must join with the new key, not a saved old one
        import network

        network.WLAN(network.STA_IF).connect(new["wifi"]["ssid"], new["wifi"]["password"])
    st["files"] = ["config.json"]
    st["version"] = "config"
    st["stage"] = "swap"
    otaboot.save(st)
    print("ota: config staged")


def last_seq() -> int:
    """The number of the last configuration taken (0: none yet, or a board deployed before numbers)."""
    try:
        with open(SEQ) as f:
            return int(f.read())
    except (OSError, ValueError):
        return 0
