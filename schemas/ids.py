"""Identifier rules shared by the site file and topic names."""

from typing import Annotated

from pydantic import StringConstraints

ID_PATTERN = r"^[A-Za-z0-9_-]{1,32}$"
"""Ids become MQTT topic levels, so they must never hold '/', '+', '#' or spaces."""

Id = Annotated[str, StringConstraints(pattern=ID_PATTERN)]
