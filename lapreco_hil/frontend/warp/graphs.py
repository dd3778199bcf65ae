"""Launches replayed from CUDA graphs, one per kind of launch sequence, shared by the front-end's frames and the
global motion prior's alignment."""

from __future__ import annotations

import logging
from typing import Callable, Hashable

import warp as wp

log = logging.getLogger(__name__)


class CapturedLaunches:
    """Each ``run(key, launches)`` replays the graph of ``key``, which is captured on the key's second run. The
    first run launches eagerly, so every kernel module is loaded and any scratch is allocated before a capture
    (neither is allowed inside one). Off CUDA, or after a capture failed (a driver without conditional graph
    nodes: CUDA < 12.4), everything is launched one by one. ``enabled`` may be switched off (profiling)."""

    def __init__(self, device, what: str) -> None:
        self.enabled = wp.get_device(device).is_cuda
        self.device = device
        self._what = what  # (for the warning)
        self._graphs: dict[Hashable, object] = {}
        self._runs: dict[Hashable, int] = {}

    @property
    def runs(self) -> dict:
        """How many times each key has run."""
        return self._runs

    @property
    def captured(self) -> set:
        """The keys that have a graph."""
        return set(self._graphs)

    def run(self, key: Hashable, launches: Callable[[], None], graphs: bool = True) -> None:
        """``launches()`` under ``key``, from its graph where there is one (``graphs``: this call may use one)."""
        graphs = graphs and self.enabled
        if graphs and self._runs.get(key, 0) >= 1 and key not in self._graphs:
            try:
                with wp.ScopedCapture(device=self.device) as capture:
                    launches()
                self._graphs[key] = capture.graph
            except Exception as exc:
                log.warning("%s: CUDA graph capture failed (%s); launching kernels one by one", self._what, exc)
                self.enabled = graphs = False
        if graphs and key in self._graphs:
            wp.capture_launch(self._graphs[key])
        else:
            launches()
        self._runs[key] = self._runs.get(key, 0) + 1
