"""The live dense stage's schedule (lapreco_hil.runtime.stages.Dense): it fuses the newest ready keyframe, leaves
the older ones to the final build, and rests in proportion to its work so it is busy at most its share of the
wall time (it shares the process with tracking). A stand-in surface records what it is asked to do; the depth
maps and fusion themselves are tested in test_dense_depth.py and test_dense_fusion.py."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np

from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.stages import Dense, StageLinks

FUSE_S = 0.04  # the stand-in's work per keyframe


class RecordingSurface:
    def __init__(self) -> None:
        self.fused: list[int] = []
        self.busy: list[tuple[float, float]] = []  # (start, end) of each fuse, monotonic s
        self.without_sources: set[int] = set()
        self.views: set[int] = set()

    def add_view(self, kf_id, image, T) -> None:
        self.views.add(kf_id)

    def fuse_pending(self, kf_ids=None) -> int:
        t0 = time.monotonic()
        time.sleep(FUSE_S)
        todo = sorted(set(kf_ids) - set(self.fused))
        self.fused += todo
        self.busy.append((t0, time.monotonic()))
        return len(todo)

    def set_depth_ranges(self, spans) -> None:
        pass

    def update_poses(self, poses) -> int:
        return 0


def _run_stage(busy_share: float, keyframes: int, seconds: float) -> tuple[RecordingSurface, LiveMetrics, float]:
    surface, links, metrics = RecordingSurface(), StageLinks(), LiveMetrics()
    stage = Dense(surface, links, metrics, period_s=None, device="cpu", busy_share=busy_share)
    frame = SimpleNamespace(image=np.zeros((4, 4, 3), np.uint8))
    thread = threading.Thread(target=stage.run)
    t0 = time.monotonic()
    thread.start()
    # keyframes arrive faster than the stage can fuse them
    for kf_id in range(keyframes):
        stage.keyframe(kf_id, frame, np.eye(4))
        time.sleep(FUSE_S / 4)
    time.sleep(max(seconds - (time.monotonic() - t0), 0.0))
    links.stop.set()
    thread.join(5.0)
    return surface, metrics, time.monotonic() - t0


def test_the_stage_fuses_the_newest_ready_keyframe_and_leaves_the_older_ones_to_the_final_build():
    surface, metrics, _ = _run_stage(busy_share=1.0, keyframes=20, seconds=0.6)
    assert surface.fused, "nothing was fused"
    # the keyframes arrived four per fuse: most were left, and what was fused rises towards the newest
    assert len(surface.fused) < 20 and surface.fused == sorted(surface.fused)
    assert surface.fused[-1] >= 17  # the newest but one is ready once the newest has come
    left = metrics.counts["dense_left_to_final"]
    assert left > 0 and left + len(surface.fused) <= 19


def test_the_stage_is_busy_at_most_its_share_of_the_wall_time():
    busy_share = 0.25
    surface, _, _ = _run_stage(busy_share=busy_share, keyframes=40, seconds=1.2)
    assert len(surface.busy) >= 3
    # from its first fuse to the start of its last, it rested three times as long as it worked
    span = surface.busy[-1][0] - surface.busy[0][0]
    work = sum(end - start for start, end in surface.busy[:-1])
    assert work / span <= busy_share * 1.15, (work, span)
    # without the rest it is busy all along while keyframes come
    full, _, _ = _run_stage(busy_share=1.0, keyframes=40, seconds=1.2)
    span = full.busy[-1][0] - full.busy[0][0]
    assert sum(end - start for start, end in full.busy[:-1]) / span >= 0.7
