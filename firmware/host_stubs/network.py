"""Test-only stand-in for the ESP8266 `network` module: the station is connected as soon as it is active
(the real ESP8266 also rejoins its saved access point by itself when config.json leaves wifi.ssid empty),
unless the file `$WSNAV_PINS/wifi_down` exists: then the access point is out of reach."""

import os


STA_IF = 0
AP_IF = 1


class WLAN:
    PM_NONE = 0

    def __init__(self, id=STA_IF):  # few names: each is a qstr the board has in ROM (firmware/device/diagnostics.py)
        self._active = id == AP_IF

    def config(self, pm):
        WLAN.pm = pm  # the radio's sleep type, global as on the ESP8266 (which boots in modem sleep, 2)

    def active(self, on=None):
        if on is not None:
            self._active = bool(on)
        return self._active

    def connect(self, ssid=None, password=None):
        pass

    def disconnect(self):
        pass

    def status(self, _):
        return -58  # 'rssi', the only status the firmware asks for

    def isconnected(self):
        try:
            os.stat((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/wifi_down")
            return False
        except OSError:
            return self._active
