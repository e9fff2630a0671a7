"""Board I/O for Wi-Fi (station mode), written so that nothing here ever waits.

`start()` asks the radio to join (modem sleep off) and returns at once, with the access point the SDK saved in
flash when it can: `connect(ssid, password)` writes the SDK's settings to flash on every call, and a node that
retries through an access-point outage would wear the flash out. Credentials go in only when the saved SSID is
not the configured one, or the last join was refused on the password (a changed Wi-Fi key), at most once a boot.
 the main loop calls `connected()` every iteration and
gives up on an attempt after its own timeout (then backs off and calls `start()` again). That keeps the
watchdog-fed main loop the only loop on the board.

`ap_after_ms` (default 5 minutes; config.json `wifi.ap_after_s`, set by app.setup; 0: never): a join begun that long after the first one that
followed the last link (or boot) opens the fallback access point instead: the marker file fallbackap.MARK, then a
reset (otaboot.boot starts fallbackap.py, not the app). The app's own offline bound (10 minutes, app.py) is
longer, so the access point opens before the watchdog would reset the board.
"""

import machine
import network
import time


class Wifi:
    def __init__(self, ssid: str, password: str, ap_after_ms: int = 300000) -> None:
        self.ssid = ssid
        self.password = password
        self.ap_after_ms = ap_after_ms
        self._lost = None  # ticks_ms of the first join since the last link (None: linked, or none tried yet)
        self._saved = False  # credentials written (to flash, by the SDK) since boot
        self._sta = network.WLAN(network.STA_IF)
        ap = network.WLAN(network.AP_IF)
        if ap.active():
            ap.active(False)  # the ESP8266 starts its own access point by default: not on a site network

    def start(self) -> None:
        """Begin (or restart) joining the access point; returns immediately (or resets into the fallback
        access point: ap_after_ms since the first join without a link)."""
        if self.ap_after_ms:
            now = time.ticks_ms()
            if self._lost is None:
                self._lost = now
            elif time.ticks_diff(now, self._lost) >= self.ap_after_ms:
                with open("wifi.fallback", "w") as f:  # fallbackap.MARK
                    f.write("1")
                print("wifi: no known network, fallback access point")
                machine.reset()
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
        if self._sta.isconnected():
            self._lost = None
            return True
        return False

    def rssi(self) -> int:
        """The signal in dBm (the SDK says 31 without a link; diagnostics leaves that out)."""
        return self._sta.status("rssi")
