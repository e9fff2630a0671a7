"""The paper's evaluation: runs of each configuration (default, zones, full) over the site's routes, their table, and the report.

Part of the wiring layer: the only place (with `wsnav/`) that drives robot_agent and zone_sim together.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.experiments import (
        cluster,
        fleet_report,
        fleet_scenario,
        fleet_sim,
        lockstep,
        report,
        run_plan,
        runner,
        single_run,
        worker,
    )

__all__ = [
    "cluster",
    "fleet_report",
    "fleet_scenario",
    "fleet_sim",
    "lockstep",
    "report",
    "run_plan",
    "runner",
    "single_run",
    "worker",
]
