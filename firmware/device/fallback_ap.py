"""The fallback access point: a node offline with no known network joined for 5 minutes (app._FALLBACK_AP_MS;
app.py writes MARK and resets) boots into this instead of the app (otaboot.boot), so the app's heap is not shared with it.

It opens `wsnav-<node>` (WPA2; the key is per node, derived from its update key: `key`, the host's
schemas.credentials.fallback_ap_key, printed by `wsnav firmware fallback-ap`) and serves one page on port 80: a
form for an SSID and a key. A good POST is tried as a configuration over the air is (otaconfig.stage: the trial,
rolled back if the node is not online with it in time; then the access point opens again). Meanwhile the station
keeps joining the known network (wifi.Wifi, every _RETRY_MS); once it joins, the node resets into the app. A
request is read within _REQUEST_MS, at most _HEAD bytes of head and _BODY of body; anything else gets a 400 and
one line, and the next request is served. A node without an update key opens no access point (it would be open),
nor one whose config.json says `"wifi": {"fallback_ap": false}`: both boot the app again.
"""

import json
import socket
import time
from hashlib import sha256

import machine
import network
import otaboot
import select
from micropython import const

MARK = "wifi.fallback"
"""The marker file (app.py writes it, this module removes it): longer than 10 characters, not interned."""
_HEAD = const(2048)
_BODY = const(256)
_REQUEST_MS = const(5000)
_RETRY_MS = const(30000)
_PAGE = (
    "<!DOCTYPE html><meta name=viewport content='width=device-width'><title>wsnav %s</title>"
    "<h1>wsnav node %s</h1><p>No known Wi-Fi network. The site's network:"
    "<form method=post><p>SSID <input name=ssid maxlength=32 required>"
    "<p>Key <input name=key type=password maxlength=64><p><button>Join</button></form>"
)


def key(update_key: str) -> str:
    """The access point's WPA2 key: 16 hex digits of sha256(update key, "wsnav-ap")."""
    return "".join("%02x" % b for b in sha256(update_key.encode() + b"wsnav-ap").digest()[:8])


def _unquote(text: bytes) -> bytes:
    """A form field's bytes (`+` a space, `%XX` a byte); ValueError on a bad escape."""
    out = bytearray()
    i = 0
    n = len(text)
    while i < n:
        c = text[i]
        if c == 43:  # +
            c = 32
        elif c == 37:  # %
            h = text[i + 1 : i + 3]
            if len(h) != 2 or h.lower().strip(b"0123456789abcdef"):
                raise ValueError("bad %-escape")
            c = int(h, 16)
            i += 2
        out.append(c)
        i += 1
    return bytes(out)


def settings(body: bytes):
    """(ssid, key) from the form's body (exactly the fields `ssid` and `key`); ValueError saying what is wrong."""
    fields = {}
    for part in body.split(b"&"):
        name, eq, value = part.partition(b"=")
        if not eq or name not in (b"ssid", b"key") or name in fields:
            raise ValueError("the form has two fields, ssid and key")
        fields[name] = _unquote(value)
    if len(fields) != 2:
        raise ValueError("the form has two fields, ssid and key")
    ssid = fields[b"ssid"]
    k = fields[b"key"]
    if not 1 <= len(ssid) <= 32:
        raise ValueError("the SSID has 1 to 32 bytes")
    if k and not (8 <= len(k) <= 63 and min(k) >= 32 and max(k) <= 126):
        raise ValueError("the key has 8 to 63 printable characters, or none")
    return ssid.decode(), k.decode()


def _request(conn, feed, buf):
    """(request line, body) of one request, gathered in `buf` (_HEAD + _BODY bytes, allocated once: no request
    builds a long object of its own, only chunks of 256 B) within _REQUEST_MS, the watchdog fed between reads;
    ValueError when it is too long, too slow, cut short or malformed."""
    n = 0
    end = -1  # where the head's blank line starts
    need = len(buf)
    t0 = time.ticks_ms()
    while n < need:
        feed()
        if time.ticks_diff(time.ticks_ms(), t0) > _REQUEST_MS:
            raise ValueError("request too slow")
        try:  # recv, not readinto: a socket's readinto waits for the whole buffer
            chunk = conn.recv(need - n if need - n < 256 else 256)
        except OSError:  # the 0.5 s timeout: no byte yet
            continue
        if not chunk:
            raise ValueError("request cut short")
        buf[n : n + len(chunk)] = chunk
        n += len(chunk)
        del chunk
        if end >= 0:
            continue
        end = buf.find(b"\r\n\r\n", 0, n)
        if end < 0 and n < _HEAD:
            continue
        if end < 0 or end + 4 > _HEAD:
            raise ValueError("request head too long")
        length = 0
        i = buf.find(b"\r\n", 0, end + 2) + 2  # the first header line (none: past `end`)
        while i < end:
            j = buf.find(b"\r\n", i, end + 2)
            if buf[i : i + 15].lower() == b"content-length:":
                length = int(bytes(buf[i + 15 : j]))  # ValueError: not a number
            i = j + 2
        if not 0 <= length <= _BODY:
            raise ValueError("body too long")
        need = end + 4 + length
    return bytes(buf[: buf.find(b"\r\n")]), bytes(buf[end + 4 : need])


def _send(conn, status: str, text: str) -> None:
    body = text.encode()
    conn.send(
        (
            "HTTP/1.0 %s\r\nContent-Type: text/html; charset=utf-8\r\nContent-Length: %d\r\n"
            "Connection: close\r\n\r\n" % (status, len(body))
        ).encode()
    )
    conn.send(body)


def handle(conn, feed, node: str, buf):
    """Answer one request (read into `buf`: _request); (ssid, key) when it brought good settings, else None."""
    try:
        line, body = _request(conn, feed, buf)
        parts = line.split()
        if len(parts) != 3 or not parts[2].startswith(b"HTTP/"):
            raise ValueError("not an HTTP request")
        method, path = parts[0], parts[1]
        if path != b"/":
            _send(conn, "404 Not Found", "no such page\n")
            return None
        if method == b"GET":
            _send(conn, "200 OK", _PAGE % (node, node))
            return None
        if method != b"POST":
            _send(conn, "405 Method Not Allowed", "GET or POST\n")
            return None
        new = settings(body)
    except ValueError as exc:
        _send(conn, "400 Bad Request", str(exc) + "\n")
        return None
    _send(
        conn,
        "200 OK",
        "<p>Trying that network. The node restarts with it; should it not get online, the"
        " old settings come back and so does this access point.\n",
    )
    return new


def _drain(conn) -> None:
    """Read what the client sent beyond its request (8 chunks of 512 B at most, 0.4 s at most), then the close
    does not reset the connection under the answer: TCP answers unread data with a reset, and the client loses
    what it was sent."""
    conn.settimeout(0.05)
    for _ in range(8):
        try:
            if not conn.recv(512):
                return
        except OSError:
            return


def open_ap(cfg):
    """The access point up and its page's socket listening: (station, access point, socket, poller, request
    buffer); None (MARK removed either way) when config.json's wifi.fallback_ap is false or the node has no
    update key."""
    with open("config.json") as f:  # not in the parsed cfg: nodeconfig keeps both out of the app's heap
        d = json.load(f)
    uk = d.get("update_key")
    off = d.get("wifi", {}).get("fallback_ap") is False
    del d
    otaboot.remove(MARK)  # whatever happens next: a power cut here boots the app, which opens us again
    if off:
        print("ap: off (wifi.fallback_ap)")
        return None
    if type(uk) is not str or len(uk) != 64:
        print("ap: no update key, no access point")
        return None
    import wifi

    sta = wifi.Wifi(cfg["wifi_ssid"], cfg["wifi_password"])  # first: it closes the SDK's own access point
    ap = network.WLAN(network.AP_IF)
    ap.active(True)
    ssid = ("wsnav-" + cfg["node"])[:32]
    ap.config(essid=ssid, password=key(uk), authmode=3)  # 3: network.AUTH_WPA2_PSK
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(socket.getaddrinfo("0.0.0.0", getattr(network, "AP_PORT", 80))[0][-1])  # AP_PORT: the tests' stub
    srv.listen(2)
    poller = select.poll()
    poller.register(srv, select.POLLIN)
    print("ap: open", ssid)
    return sta, ap, srv, poller, bytearray(_HEAD + _BODY)


def serve(cfg) -> None:
    """Open the access point and serve the page until the known network joins (reset into the app) or a good
    form is posted (its trial staged, reset). Returns only when the access point is off or cannot be opened
    (no update key; anything raised, printed): then the app runs, never the REPL. A trial still pending is
    rolled back first (otaboot.boot calls this before it counts the boot): its network did not join (a
    configuration's rollback resets; the marker stays, so the next boot comes back here)."""
    try:
        _serve(cfg)
    except Exception as exc:
        print("ap: failed,", exc)


def _serve(cfg) -> None:
    st = otaboot.load()
    if st is not None and st.get("stage") == "trial":
        otaboot.rollback(st)
    opened = open_ap(cfg)
    if opened is None:
        return
    sta, ap, srv, poller, buf = opened
    del opened
    wdt = machine.WDT()
    node = cfg["node"]
    tried = time.ticks_add(time.ticks_ms(), -_RETRY_MS)
    while True:
        wdt.feed()
        if sta.connected():
            print("ap: known network joined")
            break
        if time.ticks_diff(time.ticks_ms(), tried) >= _RETRY_MS:
            tried = time.ticks_ms()
            sta.start()
        if not poller.poll(200):
            continue
        conn = srv.accept()[0]
        new = None
        try:
            conn.settimeout(0.5)
            new = handle(conn, wdt.feed, node, buf)
            _drain(conn)
        except OSError as exc:  # the client went away mid-answer
            print("ap:", exc)
        conn.close()
        if new is not None:
            import otaconfig

            otaconfig.stage({"wifi": {"ssid": new[0], "password": new[1]}}, {"boots": 0})
            print("ap: trying", new[0])
            break
    ap.active(False)
    machine.reset()
