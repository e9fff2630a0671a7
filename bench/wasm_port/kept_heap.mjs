// What running a piece of Python keeps on the heap of the 32-bit WebAssembly port, its code compiled first: as
// for a module frozen into the board's firmware, whose bytecode and names are in flash, only what it builds at
// run time (its globals, classes, functions, instances) is counted. Bytes allocated after, less before, each
// read from JavaScript once a collection has run: this port collects only when a call from JavaScript returns
// (setup_heap.mjs says why), so a gc.collect() inside the Python frees nothing. For the parts of the board's
// boot that the node's measurement (setup_heap.mjs) does not include.
//
//     node kept_heap.mjs SNIPPET_PY
//
// Prints "kept N".
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";
import fs from "node:fs";

let out = "";
const mp = await loadMicroPython({ heapsize: 256 * 1024, stdout: (text) => { out += text + "\n"; } });
mp.FS.writeFile("/snippet.py", fs.readFileSync(process.argv[2]));
const gc = mp.pyimport("gc");
mp.runPython(`
with open("/snippet.py") as _f:
    _code = compile(_f.read(), "snippet", "exec")
_f = None
_g = {"__name__": "snippet"}
`);
gc.collect(); // runs as the call returns
const before = gc.mem_alloc();
mp.runPython("exec(_code, _g)\n"); // its own globals (_g), counted: a module's dict
gc.collect();
out += `kept ${gc.mem_alloc() - before}\n`;
process.stdout.write(out);
