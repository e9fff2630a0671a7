"""Test driver part: run_node's DNS, real or failing on demand (run_node's docstring), and its machine.reset. Its
own module, imported after run_node has measured the heap, so the node's "heap free" does not count what the
board never has. Its names and strings are chosen not to add interned strings (qstrs) the firmware does not
already have (a name the node uses, or a literal longer than 10 characters, which stays a str): on the 64-bit unix
port the node's qstrs sit just under the size at which MicroPython allocates its next qstr pool in one piece."""

import time

import machine
import mqtt

lookup = mqtt.lookup


def fake_dns(host, port):
    fault = machine._read("dns", 0)  # pyright: ignore[reportAttributeAccessIssue] (the host stub's)
    if fault:
        print(("dns down %s" if fault == 1 else "dns hang %s") % host)
        import soft_timers

        while fault == 2:
            time.sleep_ms(20)
            soft_timers._run_timers()  # lwIP's wait runs the soft timers
        raise OSError("dns down")
    return lookup(host, port, 2)  # IPv4 only, as lwIP on the ESP8266


def reset():
    """machine.reset for a `restart` command: the process ends (75, as soft_timers.reset); the test starts it
    again, as a board reboots."""
    raise SystemExit(75)


def setup():
    mqtt.lookup = fake_dns
    machine.reset = reset  # pyright: ignore[reportAttributeAccessIssue] (the stub has none)
