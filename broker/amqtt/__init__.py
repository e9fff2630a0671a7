"""`wsnav broker run`: amqtt 0.12 with our authentication, ACL, admission, framing check, retained store and
patch.
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the submodules load when imported, not with the package
    from wsnav.broker.amqtt import (
        admission,
        auth,
        config,
        embedded,
        gc_pacing,
        packet_gate,
        patch,
        retained_store,
        server,
    )

__all__ = [
    "admission",
    "auth",
    "config",
    "embedded",
    "gc_pacing",
    "packet_gate",
    "patch",
    "retained_store",
    "server",
]
