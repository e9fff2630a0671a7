"""Test-only stand-in for the ESP8266 `network` module: the station is connected as soon as it is active
(the real ESP8266 also rejoins its saved access point by itself when config.json leaves wifi.ssid empty),
unless the file `$WSNAV_PINS/wifi_down` exists or a driver sets `sdk[3]`: then the access point is out of reach;
or the file `$WSNAV_PINS/wifi_<SSID>` holds that network's key and the join used another (STAT_WRONG_PASSWORD;
no such file: any key joins). `sdk` is the SDK's flash and counters: [saved SSID, flash writes (each connect
with credentials), joins (every connect), access point out, the last join's key accepted, saved key]. What it
leaves out: scanning, DHCP, the time a join takes. Kept small: on the 38 KiB heap the stub costs what the board (ROM) never pays."""

import os

STA_IF = 0
AP_IF = 1
STAT_WRONG_PASSWORD = 2
sdk = ["", 0, 0, False, True, ""]


class WLAN:
    PM_NONE = 0

    def __init__(self, id=STA_IF):  # few names: each is a qstr the board has in ROM (firmware/device/diagnostics.py)
        self._active = id == AP_IF

    def config(self, what=None, pm=2):
        if what:
            return sdk[0]  # 'ssid', the only setting the firmware reads
        WLAN.pm = pm  # the radio's sleep type, global as on the ESP8266 (which boots in modem sleep, 2)

    def active(self, on=None):
        if on is not None:
            self._active = bool(on)
        return self._active

    def connect(self, ssid=None, password=None):
        sdk[2] += 1
        if ssid:
            sdk[0] = ssid
            sdk[5] = password
            sdk[1] += 1
        try:
            with open((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/wifi_" + sdk[0]) as f:
                sdk[4] = f.read() == sdk[5]
        except OSError:
            sdk[4] = True

    def disconnect(self):
        pass

    def status(self, what=None):
        # 'rssi' (the only status the firmware names), else STAT_GOT_IP (5) or STAT_NO_AP_FOUND (3)
        return -58 if what else 5 if self.isconnected() else 3 if sdk[4] else STAT_WRONG_PASSWORD

    def isconnected(self):
        if sdk[3] or not sdk[4]:
            return False
        try:
            os.stat((os.getenv("WSNAV_PINS") or "/tmp/wsnav-pins") + "/wifi_down")
            return False
        except OSError:
            return self._active
