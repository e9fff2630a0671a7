"""The small interfaces components meet at besides the message contract: a clock and a publish/subscribe bus.

Depends on nothing of ours but `schemas`; `robot_agent` and `zone_sim` both build on it and never on each other.
"""
