"""Test-only stand-in for the ESP8266 `network` module: the station is connected as soon as it is active
(the real ESP8266 also rejoins its saved access point by itself when config.json leaves wifi.ssid empty),
unless the file `$WSNAV_PINS/wifi_down` exists or a driver sets `WLAN.out`: then the access point is out of
reach. The SDK's flash is two class attributes: `saved` (the SSID it holds) and `writes` (each connect with
credentials writes it); `joins` counts every connect."""

import os


STA_IF = 0
AP_IF = 1
STAT_WRONG_PASSWORD = 2
STAT_NO_AP_FOUND = 3
STAT_GOT_IP = 5


class WLAN:
    PM_NONE = 0
    saved = ""
    writes = 0
    joins = 0
    out = False

    def __init__(self, id=STA_IF):  # few names: each is a qstr the board has in ROM (firmware/device/diagnostics.py)
        self._active = id == AP_IF

    def config(self, *what, pm=2):
        if what:
            return WLAN.saved  # 'ssid', the only setting the firmware reads
        WLAN.pm = pm  # the radio's sleep type, global as on the ESP8266 (which boots in modem sleep, 2)

    def active(self, on=None):
        if on is not None:
            self._active = bool(on)
        return self._active

    def connect(self, ssid=None, password=None):
        WLAN.joins += 1
        if ssid is not None:
            WLAN.saved = ssid
            WLAN.writes += 1

    def disconnect(self):
        pass

    def status(self, what=None):
        if what is None:
            return STAT_GOT_IP if self.isconnected() else STAT_NO_AP_FOUND
        return -58  # 'rssi', the only status the firmware asks for

    def isconnected(self):
        if WLAN.out:
            return False
        try:
            os.stat((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/wifi_down")
            return False
        except OSError:
            return self._active
