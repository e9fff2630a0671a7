"""The node's `config.json` (schemas/credentials.py NodeConfig, written by `wsnav broker credentials`).

Pure logic (MicroPython and CPython): `parse(dict)` checks the keys the firmware relies on and turns them into
plain attributes in the units the firmware uses (ms, mm), so a bad file fails at boot with one clear message
instead of deep in the main loop. The host validates the same file fully with pydantic before deploy.
"""

from payloads import valid_id

DIGITAL = ("pir", "ir_beam")
ULTRASONIC = "hcsr04"


class ConfigError(ValueError):
    """config.json is missing a key or holds a bad value; the message names the key."""


def _get(d, key: str, kind, default=None, where: str = ""):
    if key not in d:
        if default is None:
            raise ConfigError("config: missing key " + where + key)
        return default
    value = d[key]
    # bool is an int subclass: refuse True where a number is meant, and 1 where a bool is meant.
    if kind is bool:
        ok = value is True or value is False
    elif kind is float:
        ok = (isinstance(value, (int, float))) and not (value is True or value is False)
    else:
        ok = isinstance(value, kind) and not (kind is int and (value is True or value is False))
    if not ok:
        raise ConfigError("config: bad value for " + where + key)
    return value


def _pin(d, key: str) -> int:
    p = _get(d, key, int, where="sensor.")
    if not 0 <= p <= 16:
        raise ConfigError("config: sensor." + key + " must be a GPIO number 0..16")
    return p


class NodeConfig:
    """What the firmware needs from config.json, checked and converted."""

    def __init__(self, d) -> None:
        if not isinstance(d, dict):
            raise ConfigError("config: top level must be a JSON object")
        for key in ("site", "node", "zone", "username"):
            if not valid_id(_get(d, key, str)):
                raise ConfigError("config: " + key + " is not a valid id")
        self.site = d["site"]  # type: str
        self.node = d["node"]  # type: str
        self.zone = d["zone"]  # type: str
        self.username = d["username"]  # type: str
        self.password = _get(d, "password", str)  # type: str
        broker = _get(d, "broker", dict, {})
        self.broker_host = _get(broker, "host", str, "", "broker.")  # type: str
        if not self.broker_host:
            raise ConfigError("config: broker.host is empty (set it at deploy time)")
        self.broker_port = _get(broker, "port", int, 1883, "broker.")  # type: int
        wifi = _get(d, "wifi", dict, {})
        self.wifi_ssid = _get(wifi, "ssid", str, "", "wifi.")  # type: str
        self.wifi_password = _get(wifi, "password", str, "", "wifi.")  # type: str
        heartbeat_s = _get(d, "heartbeat_s", float)
        if not 0 < heartbeat_s <= 3600:
            raise ConfigError("config: heartbeat_s must be in (0, 3600]")
        self.heartbeat_ms = int(heartbeat_s * 1000)  # type: int
        self.on_delay_ms = _get(d, "on_delay_ms", int)  # type: int
        self.off_delay_ms = _get(d, "off_delay_ms", int)  # type: int
        if self.on_delay_ms < 0 or self.off_delay_ms < 0:
            raise ConfigError("config: on_delay_ms and off_delay_ms must be >= 0")
        self.keepalive_s = _get(d, "keepalive_s", int, 30)  # type: int
        if not 5 <= self.keepalive_s <= 3600:
            raise ConfigError("config: keepalive_s must be in [5, 3600]")
        sensor = _get(d, "sensor", dict)
        self.sensor_type = _get(sensor, "type", str, where="sensor.")  # type: str
        self.pin = -1
        self.invert = False
        self.trigger_pin = -1
        self.echo_pin = -1
        self.threshold_mm = 1000
        self.samples = 5
        if self.sensor_type in DIGITAL:
            self.pin = _pin(sensor, "pin")
            self.invert = _get(sensor, "invert", bool, False, "sensor.")
        elif self.sensor_type == ULTRASONIC:
            self.trigger_pin = _pin(sensor, "trigger_pin")
            self.echo_pin = _pin(sensor, "echo_pin")
            self.threshold_mm = int(_get(sensor, "threshold_m", float, 1.0, "sensor.") * 1000)
            self.samples = _get(sensor, "samples", int, 5, "sensor.")
            if not 1 <= self.samples <= 15:
                raise ConfigError("config: sensor.samples must be in [1, 15]")
        else:
            raise ConfigError("config: sensor.type must be pir, ir_beam or hcsr04")


def load(path: str) -> NodeConfig:
    """Read and check a config.json file."""
    import json

    try:
        with open(path) as f:
            d = json.load(f)
    except OSError:
        raise ConfigError("config: cannot read " + path)
    except ValueError:
        raise ConfigError("config: " + path + " is not valid JSON")
    return NodeConfig(d)
