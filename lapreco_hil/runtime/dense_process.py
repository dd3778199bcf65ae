"""The live dense surface in a process of its own (docs/dense.md, "Live").

In the tracking process the dense stage's work (undistorting and JPEG-encoding each keyframe, decoding the kept
images and maps, choosing sources, the depth map's and fusion's launches and read-backs) took Python's lock and
the device (one Warp stream per device per process, so the device lock) from tracking in turns. Here it runs in
a spawned process with its own interpreter, its own CUDA context and its own stream: the tracking process copies
each keyframe's image into a shared-memory slot and sends a small message; everything else happens there.

The dense process runs the stage's schedule as it was (runtime/stages.py ``Dense``: the newest ready keyframe
first, busy at most ``[runtime] dense_busy_share`` of the time, re-fusion after local BA) and sends back what the
live run reports: counters and stage times, the live mesh when the view wants one, and at the end the dense
surface built from the final map. Like the mapper it dies with the main process (``die_with_parent``); its
death is reported at once (``DenseProcessError``), never waited out.

main process -> dense process (a queue): ``KeyframeImage``, ``KeyframePoses`` (the mapper's, passed on),
``FinalBuild``, ``EndOfDense``; dense process -> main process (a pipe): ``DenseReady``, ``SlotDone``,
``DenseProgress``, ``LiveMesh``, ``DenseBuilt``, ``DenseFailed``."""

from __future__ import annotations

import collections
import logging
import multiprocessing as mp
import os
import queue
import threading
import time
import traceback
from dataclasses import dataclass

import numpy as np

from lapreco_hil.errors import LaprecoError
from lapreco_hil.runtime.messages import KeyframePoses
from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.shm import new_segment_name

log = logging.getLogger(__name__)
IMAGE_SLOTS = 8  # keyframe images in flight to the dense process (it takes each within milliseconds)
PROGRESS_PERIOD_S = 0.25  # counters and stage times are sent this often
CV2_CORE_DIVISOR = 4  # the dense process's cv2 threads: a quarter of the machine's cores (at least one)
START_TIMEOUT_S = 300.0  # for the dense process's imports, volume and kernels (compiled if the cache is cold)


class DenseProcessError(LaprecoError):
    """The live dense surface's process died or failed."""


@dataclass(frozen=True)
class DenseSpec:
    """What the dense process makes its DenseSurface and stage from (picklable: ``depth_fn`` / ``sources_fn``
    are module-level functions or objects, as ``dense.surface.stereo_functions`` gives)."""

    camera: object  # CameraModel
    config: object  # PipelineConfig
    device: str
    rig: object = None
    depth_fn: object = None
    sources_fn: object = None
    period_s: float | None = None  # the live mesh's period (None: no view wants it)
    busy_share: float = 1.0


@dataclass(frozen=True)
class KeyframeImage:
    kf_id: int
    T_world_camera: np.ndarray
    slot: int  # its image waits in this shared-memory slot; -1: the image is in ``image``
    image: np.ndarray | None = None


@dataclass(frozen=True)
class FinalBuild:
    """The finished map's keyframe poses and depth ranges: fuse every kept keyframe there and send the surface."""

    poses: dict
    ranges: dict


@dataclass(frozen=True)
class EndOfDense:
    """The dense process's stop word."""


@dataclass(frozen=True)
class DenseReady:
    pass


@dataclass(frozen=True)
class SlotDone:
    slot: int


@dataclass(frozen=True)
class DenseProgress:
    counts: dict  # counter -> increase since the last progress
    stage_s: tuple  # (stage name, seconds) timed since the last progress


@dataclass(frozen=True)
class LiveMesh:
    arrays: dict  # mesh_arrays


@dataclass(frozen=True)
class DenseBuilt:
    mesh: dict  # mesh_arrays
    stats: dict


@dataclass(frozen=True)
class DenseFailed:
    traceback: str

    @property
    def last_line(self) -> str:
        lines = self.traceback.strip().splitlines()
        return lines[-1] if lines else "unknown error"


def mesh_arrays(mesh) -> dict:
    """A pyvista mesh as plain arrays (points, faces, point data), to pickle cheaply."""
    return {"points": np.asarray(mesh.points), "faces": np.asarray(mesh.faces),
            "point_data": {name: np.asarray(mesh.point_data[name]) for name in mesh.point_data.keys()}}


def mesh_from_arrays(arrays: dict):
    import pyvista as pv

    points, faces = arrays["points"], arrays["faces"]
    mesh = pv.PolyData(points, faces) if len(faces) else pv.PolyData(points if len(points) else None)
    for name, values in arrays["point_data"].items():
        mesh.point_data[name] = values
    return mesh


class ImageSlots:
    """Shared-memory slots of one keyframe image each (H x W x 3 uint8), written by the main process and
    copied out by the dense process."""

    def __init__(self, slots: int, shape: tuple[int, int, int], name: str | None = None) -> None:
        from multiprocessing import shared_memory

        self.slots, self.shape = slots, tuple(shape)
        size = max(1, slots * int(np.prod(self.shape)))
        self.shm = shared_memory.SharedMemory(name=name or new_segment_name(), create=name is None, size=size)
        self.owner = name is None
        self.images = np.ndarray((slots, *self.shape), np.uint8, self.shm.buf)

    @property
    def name(self) -> str:
        return self.shm.name

    def close(self) -> None:
        self.images = None  # (a view into the buffer must go before the mapping can be closed)
        self.shm.close()
        if self.owner:
            self.shm.unlink()


class _StageFailed(Exception):
    """The stage's thread in the dense process raised (its traceback)."""


class _Frame:
    """What the stage reads of a keyframe's frame: its image."""

    def __init__(self, image: np.ndarray) -> None:
        self.image = image


# --- the dense process ------------------------------------------------------------------------------------------
def dense_main(spec: DenseSpec, slots_name: str, slots: int, shape: tuple, commands, answers,
               parent_pid: int) -> None:
    """Process body: the DenseSurface and the stage's schedule; commands in, progress and the surface out."""
    from lapreco_hil.runtime.mapper_process import die_with_parent

    die_with_parent(parent_pid)
    images = None
    try:
        images = ImageSlots(slots, shape, slots_name)
        _serve(spec, images, commands, answers)
    except BaseException as exc:  # every error goes back on the pipe, then the process ends
        try:
            answers.send(DenseFailed(exc.args[0] if isinstance(exc, _StageFailed) else traceback.format_exc()))
        except (BrokenPipeError, OSError):
            pass
        raise SystemExit(1)
    finally:
        if images is not None:
            images.close()


def _serve(spec: DenseSpec, images: ImageSlots, commands, answers) -> None:
    import cv2

    from lapreco_hil.dense.surface import DenseSurface
    from lapreco_hil.runtime.stages import Dense, StageLinks
    from lapreco_hil.warp_device import init_warp, preload_kernels

    # cv2's thread pool (undistortion, decoding) on a share of the cores: the tracking process keeps the others
    cv2.setNumThreads(max(1, (os.cpu_count() or 1) // CV2_CORE_DIVISOR))
    init_warp()
    surface = DenseSurface(spec.camera, spec.config, spec.device, spec.rig, spec.depth_fn, spec.sources_fn)
    # compiled and loaded now: a first depth map would otherwise wait for it mid-run
    preload_kernels("lapreco_hil.dense.warp", spec.device)
    links, metrics = StageLinks(), LiveMetrics()
    stage = Dense(surface, links, metrics, period_s=spec.period_s, device=spec.device, busy_share=spec.busy_share)
    errors: list[str] = []

    def run_stage() -> None:
        try:
            stage.run()
        except BaseException:
            errors.append(traceback.format_exc())
            links.stop.set()

    worker = threading.Thread(target=run_stage, name="dense stage", daemon=True)
    worker.start()
    progress = _Progress(metrics)
    answers.send(DenseReady())
    sent_mesh = None
    next_progress = time.monotonic() + PROGRESS_PERIOD_S
    while True:
        try:
            msg = commands.get(timeout=0.05)
        except queue.Empty:
            msg = None
        if errors:
            raise _StageFailed(errors[0])
        if isinstance(msg, KeyframeImage):
            if msg.slot >= 0:
                image = images.images[msg.slot].copy()
                answers.send(SlotDone(msg.slot))
            else:
                image = msg.image
            stage.keyframe(msg.kf_id, _Frame(image), msg.T_world_camera)
        elif isinstance(msg, KeyframePoses):
            stage.poses(msg)
        elif isinstance(msg, FinalBuild):
            links.stop.set()
            worker.join()
            if errors:
                raise _StageFailed(errors[0])
            result = stage.finish(msg.poses, msg.ranges)
            answers.send(progress.take())
            answers.send(DenseBuilt(mesh_arrays(result.mesh), result.stats))
        elif isinstance(msg, EndOfDense):
            links.stop.set()
            worker.join(timeout=10.0)
            return
        now = time.monotonic()
        if now >= next_progress:
            next_progress = now + PROGRESS_PERIOD_S
            answers.send(progress.take())
            mesh = stage.mesh
            if mesh is not None and mesh is not sent_mesh:
                sent_mesh = mesh
                answers.send(LiveMesh(mesh_arrays(mesh)))


class _Progress:
    """The dense process's counters and stage times since they were last taken."""

    def __init__(self, metrics: LiveMetrics) -> None:
        self.metrics = metrics
        self.sent_counts: collections.Counter = collections.Counter()
        self.sent_times: dict[str, int] = {}

    def take(self) -> DenseProgress:
        m = self.metrics
        counts = dict(m.counts)  # (a copy: the stage's thread bumps them)
        delta = {k: v - self.sent_counts[k] for k, v in counts.items() if v != self.sent_counts[k]}
        self.sent_counts.update(delta)
        times = []
        for name, values in list(m.stage_s.items()):
            n = len(values)
            times += [(name, s) for s in values[self.sent_times.get(name, 0):n]]
            self.sent_times[name] = n
        return DenseProgress(delta, tuple(times))


# --- the main process's side ------------------------------------------------------------------------------------
class DenseProcess:
    """The live dense stage as the main process sees it: ``keyframe`` / ``poses`` from the results stage, ``run``
    as the stage's thread (it reads the dense process's answers: counters and stage times into ``metrics``, the
    live mesh into ``mesh``, and raises DenseProcessError when the process dies or fails), ``finish`` for the
    run's dense surface from its final map, ``close`` at the end in every case."""

    def __init__(self, spec: DenseSpec, links, metrics: LiveMetrics, *, slots: int = IMAGE_SLOTS) -> None:
        self.spec, self.links, self.metrics = spec, links, metrics
        self.device = spec.device
        self.shape = (spec.camera.height, spec.camera.width, 3)
        self.n_slots = slots
        self.mesh = None
        self.process: mp.Process | None = None
        self.images: ImageSlots | None = None
        self.commands = self._answers = None
        self.free_slots: collections.deque = collections.deque(range(slots))
        self._lock = threading.Lock()  # the results stage and the run's end both send
        self._ready = False
        self._failure: str | None = None  # why the process ended, once known

    # --- life -------------------------------------------------------------------------------------------------
    def start(self) -> None:
        ctx = mp.get_context("spawn")  # (not fork: the main process has CUDA and GUI threads)
        self.images = ImageSlots(self.n_slots, self.shape)
        self.commands = ctx.Queue()
        self._answers, send = ctx.Pipe(duplex=False)
        self.process = ctx.Process(target=dense_main, name="lapreco dense", daemon=True,
                                   args=(self.spec, self.images.name, self.n_slots, self.shape, self.commands, send,
                                         os.getpid()))
        self.process.start()
        send.close()  # the dense process holds the sending end: its death reads as EOF here

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> bool:
        """Until the dense process says it is up (True). False when it died first (the stage's thread reports
        it, as any stage error) or after ``timeout_s`` (the run goes on; keyframes wait for it in its queue)."""
        deadline = time.monotonic() + timeout_s
        try:
            while not self._ready and time.monotonic() < deadline:
                self._read(0.25)
        except DenseProcessError:
            return False
        if not self._ready:
            log.warning("the dense process is not up after %.0f s; the run goes on without waiting", timeout_s)
        return self._ready

    def close(self) -> None:
        """The process ended (asked, then terminated) and the shared memory unlinked; safe to call twice."""
        if self.process is not None and self.process.pid is not None:
            if self.process.is_alive():
                try:
                    self.commands.put(EndOfDense())
                except (ValueError, OSError):
                    pass
                self.process.join(timeout=10.0)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(timeout=5.0)
        self.process = None
        if self.commands is not None:
            self.commands.close()
            self.commands.cancel_join_thread()
            self.commands = None
        if self.images is not None:
            self.images.close()
            self.images = None

    # --- from the results stage -------------------------------------------------------------------------------
    def keyframe(self, kf_id: int, frame, T_world_camera: np.ndarray) -> None:
        image = frame.image
        T = np.array(T_world_camera, float)
        with self._lock:
            if self.commands is None or self._failure is not None:
                return
            if image.shape == self.shape and image.dtype == np.uint8 and self.free_slots:
                slot = self.free_slots.popleft()
                np.copyto(self.images.images[slot], image)
                self.commands.put(KeyframeImage(kf_id, T, slot))
            else:  # every slot in flight (or an image of another shape): it goes through the queue
                self.metrics.add("dense_images_queued")
                self.commands.put(KeyframeImage(kf_id, T, -1, np.array(image)))

    def poses(self, msg: KeyframePoses) -> None:
        with self._lock:
            if self.commands is not None:
                self.commands.put(msg)

    # --- the stage's thread: the dense process's answers ------------------------------------------------------
    def run(self) -> None:
        while not self.links.finished.is_set():
            self._read(0.1)

    def _read(self, timeout_s: float):
        """Take the dense process's answers for up to ``timeout_s`` (until one arrives); returns a DenseBuilt
        when one came. DenseProcessError when the process failed or died (and at every later call)."""
        if self._failure is not None:
            raise DenseProcessError(self._failure)
        try:
            return self._take(timeout_s)
        except DenseProcessError as exc:
            self._failure = str(exc)
            raise

    def _take(self, timeout_s: float):
        try:
            if not self._answers.poll(timeout_s):
                if not self.process.is_alive():
                    raise DenseProcessError(self._death_note())
                return None
            msg = self._answers.recv()
        except (EOFError, OSError):
            self.process.join(timeout=5.0)
            raise DenseProcessError(self._death_note()) from None
        if isinstance(msg, SlotDone):
            self.free_slots.append(msg.slot)
        elif isinstance(msg, DenseProgress):
            for key, n in msg.counts.items():
                self.metrics.add(key, n)
            for name, seconds in msg.stage_s:
                self.metrics.time_stage(name, seconds)
        elif isinstance(msg, LiveMesh):
            self.mesh = mesh_from_arrays(msg.arrays)
        elif isinstance(msg, DenseReady):
            self._ready = True
        elif isinstance(msg, DenseFailed):
            raise DenseProcessError(f"the dense process failed: {msg.last_line}")
        elif isinstance(msg, DenseBuilt):
            return msg
        return None

    def _death_note(self) -> str:
        code = self.process.exitcode
        hint = " (killed: out of memory?)" if code == -9 else ""
        return f"the dense process exited (code {code}){hint}"

    # --- the run's end ----------------------------------------------------------------------------------------
    def finish(self, result):
        """The run's dense surface from its final map (every kept keyframe fused at its final pose): a
        DenseResult. Waits for the dense process as long as it lives; DenseProcessError if it dies."""
        from lapreco_hil.dense.surface import dense_result, final_poses_and_ranges

        poses, ranges = final_poses_and_ranges(result)
        with self._lock:
            self.commands.put(FinalBuild(poses, ranges))
        while (built := self._read(0.5)) is None:
            pass
        return dense_result(mesh_from_arrays(built.mesh), built.stats)
