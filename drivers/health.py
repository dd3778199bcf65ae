"""Health of a device as the pipeline sees it."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class HealthState(enum.Enum):
    DISCONNECTED = "disconnected"
    OK = "ok"
    STALE = "stale"  # connected, but no fresh data within the expected period
    FAULTED = "faulted"


@dataclass(frozen=True)
class Health:
    state: HealthState
    detail: str = ""
    t_ns: int = 0
