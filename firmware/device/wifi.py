"""Board I/O for Wi-Fi (station mode), written so that nothing here ever waits.

`start()` asks the radio to join (modem sleep off) and returns at once, with the access point the SDK saved in
flash when it can: `connect(ssid, password)` writes the SDK's settings to flash on every call, and a node that
retries through an access-point outage would wear the flash out. Credentials go in only when the saved SSID is
not the configured one, or the last join was refused on the password (a changed Wi-Fi key), at most once a boot.
 the main loop calls `connected()` every iteration and
gives up on an attempt after its own timeout (then backs off and calls `start()` again). That keeps the
watchdog-fed main loop the only loop on the board.
"""

import network


class Wifi:
    def __init__(self, ssid: str, password: str) -> None:
        self.ssid = ssid
        self.password = password
        self._saved = False  # credentials written (to flash, by the SDK) since boot
        self._sta = network.WLAN(network.STA_IF)
        ap = network.WLAN(network.AP_IF)
        if ap.active():
            ap.active(False)  # the ESP8266 starts its own access point by default: not on a site network

    def start(self) -> None:
        """Begin (or restart) joining the access point; returns immediately."""
        sta = self._sta
        sta.active(True)
        # Modem sleep off (as mqtt_as does on the ESP8266): the radio stays awake between the access point's
        # beacons, so PUBACKs and PINGRESPs are not held back to them and links drop less. Costs current.
        sta.config(pm=sta.PM_NONE)
        if self.ssid:
            try:
                sta.disconnect()
            except OSError:
                pass
            if not self._saved and (
                sta.config("ssid") != self.ssid or sta.status() == network.STAT_WRONG_PASSWORD
            ):
                self._saved = True
                sta.connect(self.ssid, self.password)
            else:
                sta.connect()  # the saved access point: nothing written

    def connected(self) -> bool:
        return self._sta.isconnected()

    def rssi(self) -> int:
        """The signal in dBm (the SDK says 31 without a link; diagnostics leaves that out)."""
        return self._sta.status("rssi")
