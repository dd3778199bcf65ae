"""The one interface every marker-tracker back-end implements (optical / electromagnetic trackers such as NDI
Polaris and Aurora): poses of tracked tools in the tracker's frame, in metres, with capture timestamps."""

from __future__ import annotations

import abc

from lapreco_hil.drivers.device import Device
from lapreco_hil.types import MarkerSample


class TrackerDriver(Device):
    """Reads tool poses (``MarkerSample``: T_tracker_marker in metres). Reading only.

    A back-end implements ``_read``; ``read`` counts what it delivers (``readings_delivered``), so a caller can
    tell a tracker that delivered nothing from one whose every reading was refused (see ``faults``: ``missing``,
    ``out_of_volume``, ``crc_errors``, ``timeouts``, ``errors``, ``disconnects``, ``reconnects``)."""

    tools: tuple[str, ...] = ()  # the names of the tools it tracks (known after open)
    _readings_delivered: int = 0

    @abc.abstractmethod
    def _read(self, timeout_s: float | None) -> list[MarkerSample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""

    def read(self, timeout_s: float | None = None) -> list[MarkerSample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""
        samples = self._read(timeout_s)
        self._readings_delivered += len(samples)
        return samples

    @property
    def readings_delivered(self) -> int:
        """How many samples ``read`` has handed out since this object was made."""
        return self._readings_delivered
