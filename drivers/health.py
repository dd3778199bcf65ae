"""Health of a device as the pipeline sees it."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class HealthState(enum.Enum):
    DISCONNECTED = "disconnected"
    OK = "ok"
    STALE = "stale"  # connected, but no fresh data within the expected period
    DEGRADED = "degraded"  # data flows, but readings are being lost (corrupt, late or missing replies)
    FAULTED = "faulted"


@dataclass(frozen=True)
class Health:
    state: HealthState
    detail: str = ""
    t_ns: int = 0
