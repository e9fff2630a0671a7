"""The paper's evaluation: runs of each configuration (default, zones, full) over the site's routes, their table, and the report.

Part of the wiring layer: the only place (with `wsnav/`) that drives robot_agent and zone_sim together.
"""
