"""Test-only stand-in for the ESP8266 `esp` module (boot.py calls esp.osdebug)."""


def osdebug(level) -> None:
    pass
