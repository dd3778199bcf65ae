"""The live dense surface's own process (lapreco_hil.runtime.dense_process): keyframe images go to it through
shared memory, it fuses them live with the stage's schedule and reports its counters, it builds the final
surface from the final poses exactly as a DenseSurface in this process would, and its death or failure is
reported at once as a DenseProcessError, never waited out. Depth maps come from a synthetic function (a wavy
surface 48-52 mm in front of each keyframe; stereo itself is tested in test_dense_depth.py); Warp's CPU device."""

from __future__ import annotations

import os
import re
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from lapreco_hil.camera import CameraModel
from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense.surface import DenseSurface, nearest_views
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.geometry import make_T
from lapreco_hil.runtime.dense_process import DenseProcess, DenseProcessError, DenseSpec
from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.stages import StageLinks

SMALL = CameraModel(160, 120, 150.0, 150.0, 79.5, 59.5)  # a pinhole keyframe: 0.5 mm voxels, 50 mm away
N_KEYFRAMES = 6


class WavyDepth:
    """A picklable depth function (the dense process unpickles it): the same wavy map whatever the pose, so a
    fusion at given poses is reproducible. ``fail``: "exit" ends the process outright at the ``fail_at``-th
    map, "raise" raises there."""

    def __init__(self, fail: str | None = None, fail_at: int = 1) -> None:
        self.fail, self.fail_at, self.calls = fail, fail_at, 0

    def __call__(self, ref, sources, depth_config, device):
        self.calls += 1
        if self.fail is not None and self.calls >= self.fail_at:
            if self.fail == "exit":
                os._exit(7)
            raise ValueError(f"no depth for keyframe {ref.kf_id}")
        ys, xs = np.mgrid[0:SMALL.height, 0:SMALL.width]
        depth = (0.05 + 0.002 * np.sin(xs / 9.0 + ref.kf_id) * np.cos(ys / 7.0)).astype(np.float32)
        return DepthMap(ref.kf_id, depth, np.full_like(depth, 0.8), ref.K, ref.T_world_camera)


def poses(n: int) -> list[np.ndarray]:
    return [make_T(np.eye(3), [0.001 * i, 0.0, 0.0]) for i in range(n)]


def images(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    return [rng.integers(0, 255, (SMALL.height, SMALL.width, 3), np.uint8) for _ in range(n)]


def final_map(Ts: list[np.ndarray]):
    """What ``finish`` reads of a finished map: keyframes with poses (and no landmarks: no depth ranges)."""
    keyframes = [SimpleNamespace(id=i, T_world_camera=T, track_ids=None) for i, T in enumerate(Ts)]
    return SimpleNamespace(keyframes=keyframes, landmark_ids=np.zeros(0, np.int64), points=np.zeros((0, 3)),
                           inlier=np.zeros(0, bool))


def start(depth_fn, config: PipelineConfig | None = None):
    links, metrics = StageLinks(), LiveMetrics()
    spec = DenseSpec(SMALL, config or PipelineConfig(), "cpu", None, depth_fn, nearest_views, period_s=0.2,
                     busy_share=1.0)
    dense = DenseProcess(spec, links, metrics, slots=2)
    dense.start()
    errors: list[BaseException] = []

    def body():
        try:
            dense.run()
        except BaseException as exc:  # (what the supervisor's guard would store)
            errors.append(exc)

    assert dense.wait_ready(120.0)
    reader = threading.Thread(target=body, daemon=True)
    reader.start()
    return dense, links, metrics, reader, errors


def test_the_dense_process_fuses_keyframes_live_and_builds_the_surface_a_local_one_would(warp_cpu):
    Ts, frames = poses(N_KEYFRAMES), images(N_KEYFRAMES)
    dense, links, metrics, reader, errors = start(WavyDepth())
    try:
        for i in range(N_KEYFRAMES):  # at once: more than the slots hold
            dense.keyframe(i, SimpleNamespace(image=frames[i]), Ts[i])
        deadline = time.monotonic() + 60.0
        while metrics.get("dense_keyframes") == 0 and time.monotonic() < deadline and not errors:
            time.sleep(0.05)
        assert not errors and metrics.get("dense_keyframes") > 0  # fused while the run goes
        assert metrics.stage_s["dense_keyframe"]  # the process's stage times reach this process's metrics
        deadline = time.monotonic() + 30.0
        while dense.mesh is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert dense.mesh is not None and dense.mesh.n_points > 0  # the live view's mesh
        # two slots for six images sent at once: some went through the queue, and every slot came back
        assert metrics.get("dense_images_queued") > 0 and len(dense.free_slots) == 2
        links.finished.set()
        reader.join(5.0)
        result = dense.finish(final_map(Ts))
    finally:
        dense.close()
    assert dense.process is None and dense.images is None  # ended and unlinked
    # the reference keyframes, each fused once, live or by the final build; the first has no older neighbour
    # but its newer one serves
    assert result.stats["keyframes_fused"] == N_KEYFRAMES
    local = DenseSurface(SMALL, PipelineConfig(), "cpu", depth_fn=WavyDepth(), sources_fn=nearest_views)
    for i in range(N_KEYFRAMES):
        local.add_view(i, frames[i], Ts[i])
    expected = local.build(final_map(Ts))
    assert len(result.points) == len(expected.points) > 1000
    order = np.lexsort(result.points.T)
    ref_order = np.lexsort(expected.points.T)
    np.testing.assert_allclose(result.points[order], expected.points[ref_order], atol=1e-9)
    np.testing.assert_array_equal(result.colours[order], expected.colours[ref_order])


@pytest.mark.parametrize("fail, message", [("exit", r"the dense process exited \(code 7\)"),
                                           ("raise", r"the dense process failed: .*ValueError: no depth for "
                                                     r"keyframe")])
def test_a_dense_process_that_dies_or_fails_is_reported_at_once(warp_cpu, fail, message):
    Ts, frames = poses(3), images(3)
    dense, links, metrics, reader, errors = start(WavyDepth(fail=fail))
    try:
        for i in range(3):
            dense.keyframe(i, SimpleNamespace(image=frames[i]), Ts[i])
        reader.join(60.0)
        assert not reader.is_alive(), "the stage's thread waited on a dead process"
        assert len(errors) == 1 and isinstance(errors[0], DenseProcessError)
        assert errors[0].args[0].count("\n") == 0  # one line
        assert re.search(message, str(errors[0])), errors[0]
        t0 = time.monotonic()
        with pytest.raises(DenseProcessError, match=message):
            dense.finish(final_map(Ts))
        assert time.monotonic() - t0 < 5.0
        dense.keyframe(3, SimpleNamespace(image=frames[0]), Ts[0])  # ignored now, not queued for nobody
    finally:
        dense.close()


def test_a_live_run_whose_dense_process_dies_stops_with_one_clear_error(tmp_path, warp_cpu, monkeypatch):
    """The whole live runtime (capture, tracking, the mapper processes) with a dense process that exits at its
    first depth map: the run stops cleanly and says which stage failed and how, instead of hanging."""
    from lapreco_hil.app.demo import run_demo
    from lapreco_hil.dense import surface as dense_surface
    from lapreco_hil.errors import LaprecoError

    monkeypatch.setattr(dense_surface, "stereo_functions", lambda: (WavyDepth(fail="exit"), nearest_views, None))
    t0 = time.monotonic()
    with pytest.raises(LaprecoError, match=r"stage 'dense' failed: DenseProcessError: the dense process exited "
                                           r"\(code 7\)$"):
        run_demo(scene="apple", frames=40, resolution=(192, 144), out=str(tmp_path), device="cpu", tracker="opencv",
                 progress=False, runtime="live", surface="dense")
    assert time.monotonic() - t0 < 120.0
