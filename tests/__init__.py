"""The wsnav test suite: real brokers, real MicroPython, real maps."""
