"""Test-only stand-in for the ESP8266 `network` module: a WLAN that is connected as soon as it is asked to be."""

STA_IF = 0
AP_IF = 1


class WLAN:
    def __init__(self, interface: int = STA_IF) -> None:
        self._active = interface == AP_IF
        self._connected = False

    def active(self, on=None):
        if on is not None:
            self._active = bool(on)
        return self._active

    def connect(self, ssid=None, password=None) -> None:
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    def isconnected(self) -> bool:
        return self._active and self._connected
