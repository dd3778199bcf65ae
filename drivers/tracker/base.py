"""The one interface every marker-tracker back-end implements (optical / electromagnetic trackers such as NDI
Polaris and Aurora): poses of tracked tools in the tracker's frame, in metres, with capture timestamps."""

from __future__ import annotations

from lapreco_hil.drivers.device import SampleStream
from lapreco_hil.types import MarkerSample


class TrackerDriver(SampleStream[MarkerSample]):
    """Reads tool poses (``MarkerSample``: T_tracker_marker in metres). Reading only.

    Its ``faults``: ``missing``, ``out_of_volume``, ``crc_errors``, ``timeouts``, ``errors``, ``disconnects``,
    ``reconnects``."""

    tools: tuple[str, ...] = ()  # the names of the tools it tracks (known after open)
