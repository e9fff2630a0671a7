"""Test driver part: run_node's DNS, real or failing on demand (run_node's docstring), and its machine.reset. Its
own module, imported after run_node has measured the heap, so the node's "heap free" does not count what the
board never has."""

import time

import machine
import mqtt

real_dns = mqtt.lookup


def fake_dns(host, port):
    fault = machine._read("dns", 0)  # pyright: ignore[reportAttributeAccessIssue] (the host stub's)
    if fault:
        print("dns", "down" if fault == 1 else "hang", host)
        import soft_timers

        while fault == 2:
            time.sleep_ms(20)
            soft_timers._run_timers()  # lwIP's wait runs the soft timers
        raise OSError("dns down")
    return real_dns(host, port, 2)  # IPv4 only, as lwIP on the ESP8266


def reset():
    """machine.reset for a `restart` command: the process ends (75, as soft_timers.reset); the test starts it
    again, as a board reboots."""
    raise SystemExit(75)


def install():
    mqtt.lookup = fake_dns
    machine.reset = reset  # pyright: ignore[reportAttributeAccessIssue] (the stub has none)
