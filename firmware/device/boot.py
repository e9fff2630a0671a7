# Runs first at every reset: quiet the ROM debug output on the UART and start with a clean heap.
import gc

import esp

esp.osdebug(None)
gc.collect()
