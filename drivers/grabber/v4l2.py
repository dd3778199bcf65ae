"""A V4L2 frame grabber through OpenCV's V4L2 back-end: one camera, a stereo pair of devices in lockstep, or one
device carrying both views of a stereo scope.

``v4l2:///dev/video0?width=1920&height=1080&fps=60&fourcc=MJPG&queue=4`` (parameters: :class:`V4L2Config`)

- mono: the device's frames as they come.
- a stereo pair, two devices (``pair=/dev/video1``): the URL's device is camera 0 (left), ``pair`` camera 1
  (right); both are opened in the same mode. Frames are paired by capture time: a left and a right frame whose
  buffer stamps are within half a frame period make one Frame (left in ``image``, right in ``views[0]``, the
  left's time and sequence number). A frame with no partner (the other device dropped or lost it) is dropped
  and counted (``unpaired_left`` / ``unpaired_right`` in ``faults``), never paired with the wrong instant.
- one device carrying both views (``layout=...``), what SDI/HDMI stereo capture delivers: ``side-by-side``
  (a 3840x1080 frame is two 1920x1080 views, left first), ``top-bottom`` (left on top), ``side-by-side-half``
  (each view squeezed to half width: a 1920x1080 frame is two 960x1080 views). The views are numpy views of
  the delivered frame (no copy; side-by-side ones are row-strided). ``width``/``height`` give the device's whole
  frame. Half-width views must be calibrated as delivered (960x1080 each): they are never resampled here, and
  a calibration made on full-width images does not apply to them.

``calib=PATH`` gives the cameras: a stereo rig file as ``lapreco calibrate stereo`` writes it (cam0_*, cam1_*,
T_cam0_cam1; see ``lapreco_hil.calib.files``) for a stereo grabber, a camera file (OpenCV or ROS camera_info
YAML) for a mono one; it becomes ``Grabber.rig`` / ``Grabber.camera``, and its image sizes must match the views.

Each device has a reader thread that takes every frame the driver delivers, stamps it with the driver's buffer
timestamp (CAP_PROP_POS_MSEC: the V4L2 buffer time, CLOCK_MONOTONIC on Linux, the app's clock), and hands it on;
the grabber keeps the newest ``queue`` frames: capture never waits on the consumer, and frames the consumer was
too slow for are counted. OpenCV does not expose the V4L2 sequence number, so frames the driver dropped are
counted from gaps in the buffer timestamps. When a device goes away (unplug), its thread reports it and reopens
it when it returns.
"""

from __future__ import annotations

import collections
import glob
import logging
import queue
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from lapreco_hil.camera import CameraModel, Rig
from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.errors import CalibrationError, DeviceError, DeviceNotFoundError, DeviceTimeoutError
from lapreco_hil.registry import URLConfig, url_param
from lapreco_hil.types import Frame

log = logging.getLogger(__name__)

MONO, SIDE_BY_SIDE, SIDE_BY_SIDE_HALF, TOP_BOTTOM = "mono", "side-by-side", "side-by-side-half", "top-bottom"
LAYOUTS = (MONO, SIDE_BY_SIDE, SIDE_BY_SIDE_HALF, TOP_BOTTOM)
# what each device's reader counts (frames read, and its faults)
DEVICE_COUNTS = ("frames", "dropped_by_driver", "reconnects", "unplugs", "stamped_on_arrival", "non_increasing_stamps")


def video_devices() -> list[str]:
    return sorted(glob.glob("/dev/video*"))


def _fourcc(text: str) -> str:
    if len(text) != 4:
        raise ValueError("must be 4 characters (e.g. MJPG, YUYV)")
    return text


def _device_path(text: str) -> str:
    if not text.startswith("/"):
        raise ValueError("must be a device path such as /dev/video1")
    return text


@dataclass(frozen=True)
class V4L2Config(URLConfig):
    width: int | None = url_param(None, low=16, high=16384, unit="px", help="frame width to ask for")
    height: int | None = url_param(None, low=16, high=16384, unit="px", help="frame height to ask for")
    fps: float | None = url_param(None, low=0.1, high=1000.0, help="frame rate to ask for")
    fourcc: str | None = url_param(None, parse=_fourcc, help="pixel format, e.g. MJPG, YUYV")
    queue: int = url_param(4, low=1, high=1000, unit="frame", help="frames held for a slow consumer")
    pair: str | None = url_param(None, parse=_device_path, help="the right camera's device of a stereo pair")
    layout: str = url_param(MONO, choices=LAYOUTS, help="how one device's frame carries a stereo scope's views")
    calib: str | None = url_param(None, help="camera file (mono) or stereo rig file (lapreco calibrate stereo)")


def _opencv_capture(device: str):
    import cv2

    return cv2.VideoCapture(device, cv2.CAP_V4L2)


def _fourcc_text(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4)) if c > 0 else "?"


def split_views(image: np.ndarray, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) views of a frame carrying both (numpy views, nothing copied)."""
    h, w = image.shape[:2]
    if layout == TOP_BOTTOM:
        return image[: h // 2], image[h // 2:]
    return image[:, : w // 2], image[:, w // 2:]


def view_size(width: int, height: int, layout: str) -> tuple[int, int]:
    """(width, height) of each view of a device frame of that size."""
    if layout == TOP_BOTTOM:
        return width, height // 2
    if layout in (SIDE_BY_SIDE, SIDE_BY_SIDE_HALF):
        return width // 2, height
    return width, height


def _load_rig(path: str, stereo: bool, url) -> Rig:
    from lapreco_hil.calib.files import read_camera_yaml, read_stereo_yaml

    if not stereo:
        return Rig.mono(read_camera_yaml(path))
    try:
        rig = read_stereo_yaml(path)
    except CalibrationError as exc:
        raise CalibrationError(f"{exc} (calib= of '{url.raw}' needs a stereo rig file: 'lapreco calibrate "
                               f"stereo' writes one)") from None
    T = rig["T_cam0_cam1"]
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: 'T_cam0_cam1' is not a rigid transform")
    return Rig((rig["cam0"], rig["cam1"]), (np.eye(4), T))


class _DeviceReader:
    """One V4L2 device: opened in the asked mode, read by a thread of its own that stamps every frame with its
    buffer time, counts the frames the driver dropped, and reopens the device after an unplug. Each frame goes
    to ``deliver(image, t_ns, seq)``."""

    def __init__(self, device: str, config: V4L2Config, grabber: "V4L2Grabber",
                 deliver: Callable[[np.ndarray, int, int], None]) -> None:
        self.device, self.config, self.grabber, self.deliver = device, config, grabber, deliver
        self._factory, self._clock, self._cv2 = grabber._factory, grabber._clock, grabber._cv2
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        self._state, self._detail = HealthState.DISCONNECTED, ""
        self._last_t_ns = 0
        self.last_arrival_ns = 0
        self._seq = 0
        self.nominal_fps: float | None = config.fps
        self.size: tuple[int, int] | None = None  # (width, height) the device gives
        self.stats = dict.fromkeys(DEVICE_COUNTS, 0)

    # --- opening and format negotiation ----------------------------------------------------------------------
    def open_capture(self):
        cap = self._factory(self.device)
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            present = video_devices()
            raise DeviceNotFoundError(f"V4L2 device '{self.device}' cannot be opened (video devices here: "
                                      f"{', '.join(present) if present else 'none'})")
        cv2, c = self._cv2, self.config
        if c.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*c.fourcc))
        if c.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
        if c.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
        if c.fps:
            cap.set(cv2.CAP_PROP_FPS, c.fps)
        got_w, got_h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        got_fps, got_cc = float(cap.get(cv2.CAP_PROP_FPS)), _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        wrong = []
        if c.width and got_w != c.width or c.height and got_h != c.height:
            wrong.append(f"size {got_w}x{got_h} (asked {c.width or got_w}x{c.height or got_h})")
        if c.fps and abs(got_fps - c.fps) > 0.01 * c.fps:
            wrong.append(f"{got_fps:g} fps (asked {c.fps:g})")
        if c.fourcc and got_cc != c.fourcc:
            wrong.append(f"format {got_cc} (asked {c.fourcc})")
        if wrong:
            cap.release()
            raise DeviceError(f"V4L2 device '{self.device}' does not support the requested mode: it gives "
                              f"{', '.join(wrong)}; pick a mode from 'v4l2-ctl -d {self.device} --list-formats-ext'")
        self.nominal_fps = got_fps or c.fps
        self.size = (got_w, got_h)
        return cap

    def start(self, cap) -> None:
        self._set_health(HealthState.OK, "")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(cap,), name=f"v4l2 {self.device}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._set_health(HealthState.DISCONNECTED, "closed")

    # --- the reader thread ---------------------------------------------------------------------------------------
    def _set_health(self, state: HealthState, detail: str) -> None:
        with self._lock:
            self._state, self._detail = state, detail

    def state(self) -> tuple[HealthState, str]:
        with self._lock:
            return self._state, self._detail

    def _run(self, cap) -> None:
        try:
            failures = 0
            while not self._stop.is_set():
                if cap is None:
                    cap = self._reconnect()
                    continue
                ok, image = cap.read()
                if not ok or image is None:
                    failures += 1
                    if failures >= self.grabber.failed_reads_for_unplug:
                        cap.release()
                        cap = None
                        self.stats["unplugs"] += 1
                        self._set_health(HealthState.DISCONNECTED, f"V4L2 device '{self.device}' stopped "
                                                                   f"delivering frames (unplugged?); reconnecting")
                        log.warning("V4L2 device '%s' lost; trying to reopen every %.1f s", self.device,
                                    self.grabber.reconnect_interval_s)
                    continue
                failures = 0
                self._take(image, cap.get(self._cv2.CAP_PROP_POS_MSEC))
            if cap is not None:
                cap.release()
        except BaseException as exc:  # surfaced by read(); never lost with the thread
            self.error = exc
            self._set_health(HealthState.FAULTED, f"reader thread of '{self.device}' failed: {exc}")

    def _reconnect(self):
        if self._stop.wait(self.grabber.reconnect_interval_s):
            return None
        try:
            cap = self.open_capture()
        except DeviceError:
            return None
        self.stats["reconnects"] += 1
        self._set_health(HealthState.OK, "reconnected")
        log.warning("V4L2 device '%s' reconnected", self.device)
        return cap

    def _stamp(self, pos_msec: float) -> int:
        now = self._clock()
        t_ns = int(round(pos_msec * 1e6)) if pos_msec and pos_msec > 0 else 0
        if t_ns == 0 or abs(now - t_ns) > self.grabber.clock_skew_limit_ns:
            self.stats["stamped_on_arrival"] += 1  # the driver's stamp is missing or on another clock
            t_ns = now
        if t_ns <= self._last_t_ns:
            self.stats["non_increasing_stamps"] += 1
            t_ns = self._last_t_ns + 1  # time never runs backwards for the consumer
        return t_ns

    def _take(self, image, pos_msec: float) -> None:
        t_ns = self._stamp(pos_msec)
        if self._last_t_ns and self.nominal_fps:
            period = 1e9 / self.nominal_fps
            gap = round((t_ns - self._last_t_ns) / period)
            if gap > 1:
                self.stats["dropped_by_driver"] += gap - 1
                self._seq += gap - 1  # sequence numbers keep their meaning: one per frame period
        self._last_t_ns = t_ns
        self.last_arrival_ns = self._clock()
        seq = self._seq
        self._seq += 1
        self.stats["frames"] += 1
        if self.state()[0] is not HealthState.OK:
            self._set_health(HealthState.OK, "")
        self.deliver(image, t_ns, seq)


class V4L2Grabber(Grabber):
    # how long a dead device is left before trying to reopen it, and how many failed reads mean "gone"
    reconnect_interval_s = 0.5
    failed_reads_for_unplug = 3
    clock_skew_limit_ns = 1_000_000_000  # a buffer stamp further than this from now is not on our clock
    # how far (capture time) one device of a pair may run ahead of the other before its oldest waiting frame is
    # given up as unpaired (the other device delivers nothing: unplugged, stalled, or its thread was held up)
    pair_wait_ns = 250_000_000

    def __init__(self, url, context) -> None:
        import cv2

        config = V4L2Config.from_url(url)
        if not url.name:
            raise url.error("give the video device, e.g. v4l2:///dev/video0")
        if config.pair is not None and config.layout != MONO:
            raise url.error(f"pair= (two devices) and layout={config.layout} (one device with both views) "
                            "exclude each other; give one")
        if config.pair == url.name:
            raise url.error(f"pair={config.pair} is the URL's own device; give the right camera's device")
        self.url = url
        self.config = config
        self.device = url.name
        self.devices = (url.name,) if config.pair is None else (url.name, config.pair)
        self.width, self.height, self.fps = config.width, config.height, config.fps
        self.fourcc, self.queue_len = config.fourcc, config.queue
        self.layout = config.layout
        self.stereo = config.pair is not None or config.layout != MONO
        # read at construction so a wrong file fails before any device is opened
        self._rig = _load_rig(config.calib, self.stereo, url) if config.calib else None
        # the capture factory is injected so the driver's logic can be tested without hardware; the clock is
        # the run's (V4L2 buffer stamps are CLOCK_MONOTONIC, the host clock's default)
        self._factory = context.options.get("v4l2_capture", _opencv_capture)
        self._clock = context.clock_ns
        self._cv2 = cv2
        self._frames: queue.Queue[Frame] = queue.Queue(maxsize=max(1, self.queue_len))
        self._readers: list[_DeviceReader] = []
        self._pending: tuple[collections.deque, collections.deque] = (collections.deque(), collections.deque())
        self._pair_lock = threading.Lock()
        self._last_arrival_ns = 0
        self.nominal_fps: float | None = self.fps
        self.max_pair_skew_ns = 0  # the largest |t_left - t_right| of a pair delivered
        self._stats = {"frames": 0, "dropped_by_consumer": 0}
        if config.pair is not None:
            self._stats.update(unpaired_left=0, unpaired_right=0)
        self._device_stats = {d: dict.fromkeys(DEVICE_COUNTS, 0) for d in self.devices}

    # --- what the grabber knows ----------------------------------------------------------------------------------
    @property
    def stats(self) -> dict[str, int]:
        """The grabber's counts (frames delivered, dropped for a slow consumer, unpaired) and its devices' counts
        summed (driver drops, unplugs, reconnects, stamps); ``device_stats`` has them per device."""
        out = dict(self._stats)
        for stats in self._device_stats.values():
            for k, v in stats.items():
                if k != "frames":
                    out[k] = out.get(k, 0) + v
        return out

    @property
    def device_stats(self) -> dict[str, dict[str, int]]:
        return {d: dict(s) for d, s in self._device_stats.items()}

    @property
    def faults(self) -> collections.Counter[str]:
        return collections.Counter({k: v for k, v in self.stats.items() if k != "frames"})

    @property
    def rig(self) -> Rig | None:
        return self._rig

    @property
    def camera(self) -> CameraModel | None:
        return self._rig.cameras[0] if self._rig is not None else None

    @classmethod
    def discover(cls) -> Discovery:
        found = video_devices()
        return Discovery("V4L2 video devices (frame grabbers)",
                         tuple(FoundDevice(d, f"v4l2://{d}?width=1920&height=1080&fps=60") for d in found),
                         "" if found else "no /dev/video* devices (is the grabber plugged in and its driver loaded?)")

    # --- opening ---------------------------------------------------------------------------------------------------
    def open(self) -> None:
        if self._readers:
            return
        if self.config.pair is None:
            sinks = [self._deliver_one]
        else:
            sinks = [lambda image, t, seq, side=side: self._deliver_side(side, image, t, seq) for side in (0, 1)]
        readers = [_DeviceReader(d, self.config, self, sink) for d, sink in zip(self.devices, sinks)]
        caps = []
        try:
            for reader in readers:
                caps.append(reader.open_capture())
            self._check_opened(readers)
        except BaseException:
            for cap in caps:
                cap.release()
            raise
        self._device_stats = {r.device: r.stats for r in readers}
        self.nominal_fps = readers[0].nominal_fps
        for pending in self._pending:
            pending.clear()
        self._readers = readers
        for reader, cap in zip(readers, caps):
            reader.start(cap)

    def _check_opened(self, readers: list[_DeviceReader]) -> None:
        """The two devices of a pair in one mode with a known rate; views the size of the calibration."""
        first = readers[0]
        if len(readers) == 2:
            second = readers[1]
            if first.size != second.size or first.nominal_fps != second.nominal_fps:
                raise DeviceError(f"V4L2 pair '{first.device}' + '{second.device}' run in different modes "
                                  f"({first.size[0]}x{first.size[1]} at {first.nominal_fps:g} fps and "
                                  f"{second.size[0]}x{second.size[1]} at {second.nominal_fps or 0:g} fps); "
                                  f"give width=, height= and fps= in the URL")
            if not first.nominal_fps:
                raise DeviceError(f"V4L2 pair '{first.device}' + '{second.device}': the devices do not say their "
                                  f"frame rate, which pairing by time needs; give fps= in the URL")
        w, h = first.size
        if self.layout != MONO and (w if self.layout != TOP_BOTTOM else h) % 2:
            raise DeviceError(f"V4L2 device '{first.device}' gives {w}x{h} frames, which do not split evenly into "
                              f"two {self.layout} views; check the mode and layout=")
        if self._rig is not None:
            size = view_size(w, h, self.layout)
            for k, cam in enumerate(self._rig.cameras):
                if (cam.width, cam.height) != size:
                    raise CalibrationError(
                        f"{self.config.calib}: camera {k} is calibrated at {cam.width}x{cam.height} but "
                        f"'{self.url.raw}' delivers {size[0]}x{size[1]} views; calibrate in this mode "
                        f"(or fix width=/height=/layout=)")

    def close(self) -> None:
        for reader in self._readers:
            reader.stop()
        self._readers = []

    # --- frames from the reader threads ----------------------------------------------------------------------------
    def _deliver_one(self, image: np.ndarray, t_ns: int, seq: int) -> None:
        views: tuple[np.ndarray, ...] = ()
        if self.layout != MONO:
            image, right = split_views(image, self.layout)
            views = (right,)
        self._put(Frame(image=image, t_ns=t_ns, seq=seq, host_ns=t_ns, views=views))  # (t_ns: monotonic clock)

    def _deliver_side(self, side: int, image: np.ndarray, t_ns: int, seq: int) -> None:
        """A frame of one device of a pair: paired with the other's frame of the same instant, or dropped."""
        tolerance_ns = 0.5e9 / self.nominal_fps
        with self._pair_lock:
            left, right = self._pending
            self._pending[side].append((image, t_ns, seq))
            pairs = []
            while left and right:
                dt = left[0][1] - right[0][1]
                if abs(dt) <= tolerance_ns:
                    pairs.append((left.popleft(), right.popleft()))
                    self.max_pair_skew_ns = max(self.max_pair_skew_ns, abs(dt))
                elif dt < 0:  # the left frame's partner never came: the right one is of a later instant
                    left.popleft()
                    self._stats["unpaired_left"] += 1
                else:
                    right.popleft()
                    self._stats["unpaired_right"] += 1
            for pending, key in ((left, "unpaired_left"), (right, "unpaired_right")):
                while pending and pending[-1][1] - pending[0][1] > self.pair_wait_ns:
                    pending.popleft()
                    self._stats[key] += 1
            for (image0, t0, seq0), (image1, _, _) in pairs:  # (under the lock: both readers deliver)
                self._put(Frame(image=image0, t_ns=t0, seq=seq0, host_ns=t0, views=(image1,)))

    def _put(self, frame: Frame) -> None:
        self._last_arrival_ns = self._clock()
        self._stats["frames"] += 1
        try:
            self._frames.put_nowait(frame)
        except queue.Full:
            try:
                self._frames.get_nowait()  # the consumer is behind: the oldest frame goes
                self._stats["dropped_by_consumer"] += 1
            except queue.Empty:
                pass
            self._frames.put_nowait(frame)

    # --- the consumer's side ----------------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> Frame | None:
        for reader in self._readers:
            if reader.error is not None:
                raise DeviceError(f"V4L2 device '{reader.device}': reader failed: {reader.error}") from reader.error
        if not self._readers:
            raise DeviceError(f"V4L2 device '{self.device}' is not open")
        try:
            return self._frames.get(timeout=timeout_s)
        except queue.Empty:
            raise DeviceTimeoutError(f"V4L2 device '{self.device}': no frame within {timeout_s} s "
                                     f"({self.health.state.value}: {self.health.detail or 'no detail'})") from None

    @property
    def health(self) -> Health:
        now = self._clock()
        if not self._readers:
            return Health(HealthState.DISCONNECTED, "closed", now)
        states = [reader.state() for reader in self._readers]
        worst = next((s for s in states if s[0] is HealthState.FAULTED), None) or \
            next((s for s in states if s[0] is not HealthState.OK), None)
        if worst is not None:
            return Health(worst[0], worst[1], now)
        detail = states[0][1]
        if self._last_arrival_ns and self.nominal_fps and now - self._last_arrival_ns > 3e9 / self.nominal_fps:
            unpaired = f" (frames unpaired: {self._stats['unpaired_left']} left, {self._stats['unpaired_right']} " \
                       f"right)" if self.config.pair is not None else ""
            return Health(HealthState.STALE, f"no frame for {(now - self._last_arrival_ns) * 1e-6:.0f} ms{unpaired}",
                          now)
        return Health(HealthState.OK, detail, now)
