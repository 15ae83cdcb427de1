"""The liveness probe's answer."""

from __future__ import annotations

from typing import Literal

from service.api.schemas.base import Schema


class Liveness(Schema):
    """The service answers."""

    status: Literal["ok"]
    """Always ``"ok"``."""
