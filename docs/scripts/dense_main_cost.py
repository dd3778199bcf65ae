"""Main-process cost of the dense stage per keyframe now: DenseProcess.keyframe (copy into a slot, a message) and
the answers' reader thread (CPU time). 1080p frames from the session; the dense process does its real host work.

usage: python docs/scripts/dense_main_cost.py SESSION"""
import sys, threading, time, statistics
import numpy as np
from types import SimpleNamespace
from lapreco_hil.config import PipelineConfig
from lapreco_hil.dense.surface import nearest_views
from lapreco_hil.dense.types import DepthMap
from lapreco_hil.runtime.dense_process import DenseProcess, DenseSpec
from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.stages import StageLinks
from lapreco_hil.sessions import format as fmt
from lapreco_hil.sessions.session import Session


class PlaneDepth:
    """A flat stand-in depth map 10 cm away (the stage's host work and fusion without stereo)."""

    def __call__(self, ref, sources, cfg, device):
        h, w = ref.colour.shape[:2]
        d = (np.full((h, w), 0.1, np.float32) * ref.mask).astype(np.float32)
        return DepthMap(ref.kf_id, d, ref.mask.astype(np.float32), ref.K, ref.T_world_camera)


class NoDepth:
    """No depth map: the stage's host work only (undistortion, JPEG, source choice and decoding)."""

    def __call__(self, ref, sources, cfg, device):
        return None

def main():
    s = Session(sys.argv[1])
    t_ns, poses = fmt.read_pose_table(s.folder / "truth" / "camera_poses.csv", 1.0)
    pose_at = dict(zip(t_ns.tolist(), poses))
    links, metrics = StageLinks(), LiveMetrics()
    spec = DenseSpec(s.camera, PipelineConfig(), "cpu", None, PlaneDepth(), nearest_views, period_s=None, busy_share=1.0)
    d = DenseProcess(spec, links, metrics); d.start(); print("ready", d.wait_ready())
    cpu = {}
    def reader():
        t0 = time.thread_time(); d.run(); cpu["reader"] = time.thread_time() - t0
    th = threading.Thread(target=reader); th.start()
    frames = [s.frame(i).image for i in range(len(s.frame_t_ns))]
    calls = []
    t_run = time.perf_counter()
    for i, img in enumerate(frames):
        T = pose_at[int(s.frame_t_ns[i])]
        t0 = time.perf_counter(); c0 = time.thread_time()
        d.keyframe(i, SimpleNamespace(image=img), T)
        calls.append((time.perf_counter() - t0, time.thread_time() - c0))
        time.sleep(0.1)
    wall = time.perf_counter() - t_run
    links.finished.set(); th.join()
    d.close()
    w = [c[0] * 1e3 for c in calls]; c = [c[1] * 1e3 for c in calls]
    print(f"keyframe(): wall mean {statistics.mean(w):.2f} ms (max {max(w):.2f}), CPU {statistics.mean(c):.2f} ms; "
          f"reader thread CPU {cpu['reader'] * 1e3 / len(frames):.2f} ms per keyframe over {wall:.1f} s; "
          f"queued {metrics.get('dense_images_queued')}, fused live {metrics.get('dense_keyframes')}")
if __name__ == "__main__":
    main()
