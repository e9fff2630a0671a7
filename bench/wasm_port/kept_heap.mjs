// What running a piece of Python keeps on the heap of the 32-bit WebAssembly port, its code compiled first: as
// for a module frozen into the board's firmware, whose bytecode and names are in flash, only what it builds at
// run time (its globals, classes, functions, instances) is counted. Bytes allocated after, less before, each after
// gc.collect(). For the parts of the board's boot that the node's measurement (setup_heap.mjs) does not include.
//
//     node kept_heap.mjs SNIPPET_PY
//
// Prints "kept N".
import { loadMicroPython } from "@micropython/micropython-webassembly-pyscript/micropython.mjs";
import fs from "node:fs";

let out = "";
const mp = await loadMicroPython({ heapsize: 256 * 1024, stdout: (text) => { out += text + "\n"; } });
mp.FS.writeFile("/snippet.py", fs.readFileSync(process.argv[2]));
mp.runPython(`
import gc
with open("/snippet.py") as _f:
    _code = compile(_f.read(), "snippet", "exec")
_f = None
_before = 0
gc.collect()
_before = gc.mem_alloc()
exec(_code, {"__name__": "snippet"})  # its own globals, counted: a module's dict
gc.collect()
print("kept", gc.mem_alloc() - _before)
`);
process.stdout.write(out);
