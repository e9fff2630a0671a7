// The zone node set up on a 32-bit MicroPython with a 38 KiB heap: MicroPython's WebAssembly port (same release
// as the unix port the tests use), whose objects have the ESP8266's sizes (4-byte pointers, 16-byte GC blocks),
// where the 64-bit unix port's are larger.
//
//     node setup_heap.mjs BUILD_DIR CONFIG_JSON [MANIFEST_JSON | SCRIPT_PY [DATA_FILE]]
//
// machine, network, socket and select are JavaScript modules: like the board's, which are in ROM, they take
// (almost) nothing from the heap; each object the firmware keeps from them (a Pin, a WLAN) is one small proxy
// object, as on the board. Then main.py's sequence: parse the config, drop the parser, import app (which
// imports the rest one module at a time), and app.setup builds the node as app.main does. Prints one line,
// "heap used U free F total T bare B largest L" (bytes, after a collection; bare: used before anything is
// imported; largest: the largest free block, which bounds the biggest message the node can still build; with a
// manifest, update mode's instead, and "setup_free S" before the transfer; with a .py script, that script run
// from source instead of the sequence below: bench/firmware_heap.py's main.py up to the node's setup), or
// "error ..." when the node does not set up. DATA_FILE, with a script: put at /data.bin for it (a sealed
// configuration, bench/firmware_ota.py).
//
// This port collects only between calls from JavaScript: inside one runPython, gc.collect() merely marks a
// collection for when the call returns (ports/webassembly/main.c, MICROPY_GC_SPLIT_HEAP_AUTO: its C stack
// cannot be scanned). So every figure here is taken from JavaScript after the call, once the collection has
// run; a sequence is run in parts (split at "#---" lines), with a real collection between them where the board
// collects. Inside a part nothing is freed, and where the board would collect (an allocation that does not fit)
// this port adds heap instead: then the line ends "grew N" (bytes added), free is still the 38 KiB heap's total
// less what is kept after the collection, and largest is at most that free. What is kept is all that must fit:
// more than the 38 KiB heap holds is reported as an error.
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";
import fs from "node:fs";

const [buildDir, configPath, manifestPath, dataPath] = process.argv.slice(2);
let out = "";
const mp = await loadMicroPython({
  heapsize: 38 * 1024,
  // a script's own figures: a line it prints starting "bench " is passed on (bench/firmware_ota.py)
  stdout: (text) => { if (text.startsWith("bench ")) console.log(text.slice(6)); else out += text + "\n"; },
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
if (dataPath) mp.FS.writeFile("/data.bin", fs.readFileSync(dataPath));

const gc = mp.pyimport("gc");
const micropython = mp.pyimport("micropython");
mp.runPython("import gc\nimport micropython\n");
gc.collect(); // collected as the call returns: this and every reading below are made from JavaScript
const bare = gc.mem_alloc();
const heapTotal = () => {
  out = "";
  micropython.mem_info(); // gc.mem_free() counts the room the port could still add; "GC: total" is the heap
  return Number(/GC: total: (\d+)/.exec(out)[1]);
};
const total = heapTotal();
const node = `
import sys
import nodeconfig
CFG = nodeconfig.load("/config.json")
del nodeconfig
del sys.modules["nodeconfig"]
gc.collect()
#---
import app
node = app.setup(CFG)
gc.collect()
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
#---
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
`;
const script = manifestPath && manifestPath.endsWith(".py") ? fs.readFileSync(manifestPath, "utf8") : null;
if (manifestPath && !script) mp.FS.writeFile("/manifest.json", fs.readFileSync(manifestPath));
// A script (main.py's path) is compiled in a call of its own and kept, then run: on the board main.py's bytecode
// stays referenced while it runs (app.main never returns), its compiler's temporaries do not. What the script has
// after a "#---" line runs after that, a call each (bench/firmware_heap.py fills the node's log ring so).
const [mainScript, ...after] = script ? script.split("#---\n") : [""];
if (script) mp.FS.writeFile("/main_setup.py", mainScript);
const run = 'with open("/main_setup.py") as f:\n    _main = compile(f.read(), "main.py", "exec")\n#---\nexec(_main)\n';
const parts = script ? [...run.split("#---\n"), ...after] : (manifestPath ? update : node).split("#---\n");
const kept = [];
try {
  for (const part of parts) {
    mp.runPython(part);
    gc.collect(); // marks one if the part did not: it runs as this call returns
    kept.push(gc.mem_alloc());
  }
} catch (err) {
  console.log("error " + String(err.message || err).trim().split("\n").pop());
  process.exit(0);
}
const now = heapTotal();
const largest = 16 * Number(/max free sz: (\d+)/.exec(out)[1]); // in 16-byte GC blocks
const used = kept[kept.length - 1];
if (Math.max(...kept) > total) {
  console.log(`error ${Math.max(...kept)} bytes kept after a collection, more than the ${total} of a 38 KiB heap`);
} else {
  const more = (manifestPath && !script ? ` setup_free ${total - kept[0]}` : "") + (now > total ? ` grew ${now - total}` : "");
  const big = now > total ? Math.min(largest, total - used) : largest;
  console.log(`heap used ${used} free ${total - used} total ${total} bare ${bare} largest ${big}${more}`);
}
