"""The operator's console: a live web page and terminal commands over the site's MQTT contract."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.console import (
        auth,
        cli,
        live_state,
        operator_commands,
        operator_link,
        serve,
        site_view,
        terminal,
        web_app,
    )

__all__ = [
    "auth",
    "cli",
    "live_state",
    "operator_commands",
    "operator_link",
    "serve",
    "site_view",
    "terminal",
    "web_app",
]
