"""The node's `config.json` (schemas/credentials.py NodeConfig, written by `wsnav broker credentials`).

Pure logic (MicroPython and CPython): `parse(dict)` checks the keys the firmware relies on and turns them into
plain attributes in the units the firmware uses (ms, mm), so a bad file fails at boot with one clear message
instead of deep in the main loop. The host validates the same file fully with pydantic before deploy.
"""

def valid_id(text) -> bool:
    """True if `text` is a contract id (a topic level without separators or wildcards)."""
    if not isinstance(text, str) or not 1 <= len(text) <= 32:
        return False
    for (
        c
    ) in text:  # by code point: one-letter literals would be interned on the board for good (diagnostics.py)
        o = ord(c)
        if not (97 <= o <= 122 or 65 <= o <= 90 or 48 <= o <= 57 or o == 95 or o == 45):
            return False
    return True


class ConfigError(ValueError):
    """config.json is missing a key or holds a bad value; the message names the key."""


def _raw(d, key: str, default, where: str):
    if key in d:
        return d[key]
    if default is None:
        raise ConfigError("config: missing key " + where + key)
    return default


def _bad(where: str, key: str, kind: str) -> ConfigError:
    """`kind` says " must be ...": literals longer than 10 characters are not interned when the module loads,
    so they leave the board's heap with it (diagnostics.py says why that counts)."""
    return ConfigError("config: " + where + key + kind)


def _str(d, key: str, default=None, where: str = "") -> str:
    v = _raw(d, key, default, where)
    if not isinstance(v, str):
        raise _bad(where, key, " must be a string")
    return v


def _int(d, key: str, default=None, where: str = "") -> int:
    v = _raw(d, key, default, where)
    if not isinstance(v, int) or isinstance(v, bool):  # JSON true is not a number here
        raise _bad(where, key, " must be an integer")
    return v


def _num(d, key: str, default=None, where: str = "") -> float:
    v = _raw(d, key, default, where)
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        raise _bad(where, key, " must be a number")
    return v


def _bool(d, key: str, default=None, where: str = "") -> bool:
    v = _raw(d, key, default, where)
    if not isinstance(v, bool):
        raise _bad(where, key, " must be true or false")
    return v


def _dict(d, key: str, default=None, where: str = "") -> dict:
    v = _raw(d, key, default, where)
    if not isinstance(v, dict):
        raise _bad(where, key, " must be an object")
    return v


def _pin(d, key: str, unsafe) -> int:
    """Refuses the serial console (GPIO1, 3) and the SPI flash (GPIO6-11); inputs also avoid the boot-mode pins
    0, 2, 15 and an IR receiver GPIO16 (no pull-up). One message for all, and no module-level names: each extra
    string or name stays on the heap as an interned qstr after this module is dropped; `wsnav site check`
    (schemas/site_file.py `pin_problem`) names the exact problem."""
    p = _int(d, key, where="sensor.")
    if not 0 <= p <= 16 or p in (1, 3, 6, 7, 8, 9, 10, 11) or p in unsafe:
        raise ConfigError(
            "config: sensor." + key + " must be a GPIO the sensor can use (wsnav site check says why)"
        )
    return p


def parse(d) -> dict:
    """What the firmware needs from config.json, checked and converted, as a flat dict.

    A dict, not an instance: an instance would keep its class, and through it this whole module, alive; the
    board drops this module after boot to give its heap back to the MQTT client.
    """
    c = {}
    if not isinstance(d, dict):
        raise ConfigError("config: top level must be a JSON object")
    for key in ("site", "node", "zone", "username"):
        if not valid_id(_str(d, key)):
            raise ConfigError("config: " + key + " is not a valid id")
    c["site"] = d["site"]
    c["node"] = d["node"]
    c["zone"] = d["zone"]
    c["username"] = d["username"]
    c["password"] = _str(d, "password")
    broker = _dict(d, "broker", {})
    c["broker_host"] = _str(broker, "host", "", "broker.")
    if not c["broker_host"]:
        raise ConfigError("config: broker.host is empty (set it at deploy time)")
    c["broker_port"] = _int(broker, "port", 1883, "broker.")
    wifi = _dict(d, "wifi", {})
    c["wifi_ssid"] = _str(wifi, "ssid", "", "wifi.")
    c["wifi_password"] = _str(wifi, "password", "", "wifi.")
    heartbeat_s = _num(d, "heartbeat_s")
    if not 0 < heartbeat_s <= 3600:
        raise ConfigError("config: heartbeat_s must be in (0, 3600]")
    c["heartbeat_ms"] = int(heartbeat_s * 1000)
    c["on_delay_ms"] = _int(d, "on_delay_ms")
    c["off_delay_ms"] = _int(d, "off_delay_ms")
    if c["on_delay_ms"] < 0 or c["off_delay_ms"] < 0:
        raise ConfigError("config: on_delay_ms and off_delay_ms must be >= 0")
    c["keepalive_s"] = _int(d, "keepalive_s", 30)
    if not 5 <= c["keepalive_s"] <= 3600:
        raise ConfigError("config: keepalive_s must be in [5, 3600]")
    sensor = _dict(d, "sensor")
    c["sensor_type"] = _str(sensor, "type", where="sensor.")
    c["pin"] = -1
    c["invert"] = False
    c["trigger_pin"] = -1
    c["echo_pin"] = -1
    c["threshold_mm"] = 1000
    c["caution_mm"] = 0
    c["samples"] = 5
    c["warmup_ms"] = 0
    if c["sensor_type"] in ("pir", "ir_beam"):
        c["pin"] = _pin(sensor, "pin", (0, 2, 15, 16) if c["sensor_type"] == "ir_beam" else (0, 2, 15))
        c["invert"] = _bool(sensor, "invert", False, "sensor.")
        if c["sensor_type"] == "pir":  # absent or null: an HC-SR501's 60 s
            warmup = sensor.get("warmup_s")
            c["warmup_ms"] = int((60 if warmup is None else _num(sensor, "warmup_s", where="sensor.")) * 1000)
            if not 0 <= c["warmup_ms"] <= 600000:
                raise ConfigError("config: sensor.warmup_s must be in [0, 600]")
    elif c["sensor_type"] == "hcsr04":
        c["trigger_pin"] = _pin(sensor, "trigger_pin", ())
        c["echo_pin"] = _pin(sensor, "echo_pin", (0, 2, 15, c["trigger_pin"]))
        c["threshold_mm"] = int(_num(sensor, "threshold_m", 1.0, "sensor.") * 1000)
        c["samples"] = _int(sensor, "samples", 5, "sensor.")
        if not 1 <= c["samples"] <= 15:
            raise ConfigError("config: sensor.samples must be in [1, 15]")
        if sensor.get("caution_m") is not None:  # absent or null: no caution band
            c["caution_mm"] = int(_num(sensor, "caution_m", where="sensor.") * 1000)
            if not c["threshold_mm"] < c["caution_mm"] <= 4000:
                raise ConfigError("config: sensor.caution_m must be beyond threshold_m and at most 4")
    else:
        raise ConfigError("config: sensor.type must be pir, ir_beam or hcsr04")
    return c


def load(path: str) -> dict:
    """Read and check a config.json file."""
    import json

    try:
        with open(path) as f:
            d = json.load(f)
    except OSError:
        raise ConfigError("config: cannot read " + path)
    except ValueError:
        raise ConfigError("config: " + path + " is not valid JSON")
    return parse(d)
