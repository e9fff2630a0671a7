// The zone node set up on a 32-bit MicroPython with a 38 KiB heap: MicroPython's WebAssembly port (same release
// as the unix port the tests use), whose objects have the ESP8266's sizes (4-byte pointers, 16-byte GC blocks),
// where the 64-bit unix port's are larger.
//
//     node setup_heap.mjs BUILD_DIR CONFIG_JSON [MANIFEST_JSON | SCRIPT_PY]
//
// machine, network, socket and select are JavaScript modules: like the board's, which are in ROM, they take
// (almost) nothing from the heap; each object the firmware keeps from them (a Pin, a WLAN) is one small proxy
// object, as on the board. Then main.py's sequence: parse the config, drop the parser, import app (which
// imports the rest one module at a time), and app.setup builds the node as app.main does. Prints one line,
// "heap used U free F total T bare B largest L" (bytes, after gc.collect(); bare: used before anything is
// imported; largest: the largest free block, which bounds the biggest message the node can still build; with a
// manifest, update mode's instead, and "setup_free S" before the transfer; with a .py script, that script run
// from source instead of the sequence below: bench/firmware_heap.py's main.py up to the node's setup), or
// "error ..." when the node does not set up. The port's heap would grow by itself past 38 KiB; a total other than the first one is reported as
// an error, so a number is always what a 38 KiB heap holds.
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";
import fs from "node:fs";

const [buildDir, configPath, manifestPath] = process.argv.slice(2);
let out = "";
const mp = await loadMicroPython({
  heapsize: 38 * 1024,
  stdout: (text) => { out += text + "\n"; },
  stderr: (text) => { out += text + "\n"; },
});

const pin = () => ({ value: (v) => (v === undefined ? 0 : undefined) });
pin.IN = 0;
pin.OUT = 1;
pin.PULL_UP = 1;
mp.registerJsModule("machine", {
  Pin: pin,
  time_pulse_us: () => -1,
  reset_cause: () => 0,
  WDT: () => ({ feed: () => undefined }),
});
const wlan = (id) => {
  let active = id === 1; // the ESP8266 starts its access point, not its station
  return {
    PM_NONE: 0,
    active: (on) => { if (on !== undefined) active = Boolean(on); return active; },
    isconnected: () => false,
    status: () => 31,
    connect: () => undefined,
    disconnect: () => undefined,
    config: () => undefined,
  };
};
// The fallback access point's (fallback_ap.open_ap) listening socket and poller: one small object each, as above.
mp.registerJsModule("network", { STA_IF: 0, AP_IF: 1, WLAN: wlan });
const sock = () => ({ setsockopt: () => undefined, bind: () => undefined, listen: () => undefined });
const addr = () => [[2, 1, 0, "", ["0.0.0.0", 80]]];
mp.registerJsModule("socket", { SOL_SOCKET: 1, SO_REUSEADDR: 4, getaddrinfo: addr, socket: sock });
mp.registerJsModule("select", { POLLIN: 1, POLLHUP: 16, POLLERR: 8, poll: () => ({ register: () => undefined }) });

mp.FS.mkdirTree("/lib");
for (const name of fs.readdirSync(buildDir)) {
  if (name.endsWith(".mpy")) mp.FS.writeFile("/lib/" + name, fs.readFileSync(buildDir + "/" + name));
}
mp.FS.writeFile("/config.json", fs.readFileSync(configPath));

mp.runPython(`
import gc
import micropython
gc.collect()
_bare = gc.mem_alloc()
micropython.mem_info()
`);
const total = Number(/GC: total: (\d+)/.exec(out)[1]);
out = "";
const node = `
import sys
import nodeconfig
CFG = nodeconfig.load("/config.json")
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
import app
node = app.setup(CFG)
gc.collect()
_used = gc.mem_alloc()
micropython.mem_info()
print("heap used", _used, "bare", _bare)
`;
// Update mode (firmware/device/updater.py), as main.py enters it: config parsed and its parser dropped, otaboot
// loaded (it calls the updater), the updater's link built and Wi-Fi's module loaded ("setup"); then what the
// transfer holds at its peak: the manifest's files (parsed from the flash, as updater.py does), a view of the
// chunk buffer's data, the sha256 and the open .tmp file.
const update = `
import sys
import nodeconfig
CFG = nodeconfig.load("/config.json")
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
import otaboot
import updater
link = updater.Fetcher(CFG)
import wifi
w = wifi.Wifi(CFG["wifi_ssid"], CFG["wifi_password"])
gc.collect()
_setup = gc.mem_alloc()
import hashlib
import json
with open("/manifest.json") as f:
    manifest = json.load(f)
files = [(x["name"], x["size"], x["sha256"]) for x in manifest["files"]]
del manifest
data = link.client.buf[10:]
h = hashlib.sha256()
h.update(data)
out = open("/x.tmp", "wb")
out.write(data)
gc.collect()
_used = gc.mem_alloc()
micropython.mem_info()
print("heap used", _used, "bare", _bare, "setup", _setup)
`;
const script = manifestPath && manifestPath.endsWith(".py") ? fs.readFileSync(manifestPath, "utf8") : null;
if (manifestPath && !script) mp.FS.writeFile("/manifest.json", fs.readFileSync(manifestPath));
try {
  mp.runPython(script || (manifestPath ? update : node));
} catch (err) {
  console.log("error " + String(err.message || err).trim().split("\n").pop());
  process.exit(0);
}
const now = Number(/GC: total: (\d+)/.exec(out)[1]);
const used = /heap used (\d+) bare (\d+)/.exec(out);
const largest = 16 * Number(/max free sz: (\d+)/.exec(out)[1]); // in 16-byte GC blocks
const setup = / setup (\d+)/.exec(out);
if (now !== total) {
  console.log(`error the heap grew past ${total} bytes (to ${now}): the node does not fit`);
} else {
  const more = setup ? ` setup_free ${total - Number(setup[1])}` : "";
  console.log(`heap used ${used[1]} free ${total - Number(used[1])} total ${total} bare ${used[2]} largest ${largest}${more}`);
}
