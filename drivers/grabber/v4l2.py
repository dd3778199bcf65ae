"""A V4L2 frame grabber through OpenCV's V4L2 back-end.

``v4l2:///dev/video0?width=1920&height=1080&fps=60&fourcc=MJPG&queue=4`` (parameters: :class:`V4L2Config`)

A reader thread takes every frame the driver delivers, stamps it with the driver's buffer timestamp
(CAP_PROP_POS_MSEC: the V4L2 buffer time, CLOCK_MONOTONIC on Linux, the app's clock), and keeps the newest
``queue`` frames: capture never waits on the consumer, and frames the consumer was too slow for are counted.
OpenCV does not expose the V4L2 sequence number, so frames the driver dropped are counted from gaps in the
buffer timestamps. When the device goes away (unplug), the thread reports it and reopens it when it returns.
"""

from __future__ import annotations

import collections
import glob
import logging
import queue
import threading
from dataclasses import dataclass

from lapreco_hil.drivers.device import Discovery, FoundDevice
from lapreco_hil.drivers.health import Health, HealthState
from lapreco_hil.drivers.grabber.base import Grabber
from lapreco_hil.errors import DeviceError, DeviceNotFoundError, DeviceTimeoutError
from lapreco_hil.registry import URLConfig, url_param
from lapreco_hil.types import Frame

log = logging.getLogger(__name__)


def video_devices() -> list[str]:
    return sorted(glob.glob("/dev/video*"))


def _fourcc(text: str) -> str:
    if len(text) != 4:
        raise ValueError("must be 4 characters (e.g. MJPG, YUYV)")
    return text


@dataclass(frozen=True)
class V4L2Config(URLConfig):
    width: int | None = url_param(None, low=16, high=16384, unit="px", help="frame width to ask for")
    height: int | None = url_param(None, low=16, high=16384, unit="px", help="frame height to ask for")
    fps: float | None = url_param(None, low=0.1, high=1000.0, help="frame rate to ask for")
    fourcc: str | None = url_param(None, parse=_fourcc, help="pixel format, e.g. MJPG, YUYV")
    queue: int = url_param(4, low=1, high=1000, unit="frame", help="frames held for a slow consumer")


def _opencv_capture(device: str):
    import cv2

    return cv2.VideoCapture(device, cv2.CAP_V4L2)


def _fourcc_text(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4)) if c > 0 else "?"


class V4L2Grabber(Grabber):
    # how long a dead device is left before trying to reopen it, and how many failed reads mean "gone"
    reconnect_interval_s = 0.5
    failed_reads_for_unplug = 3
    clock_skew_limit_ns = 1_000_000_000  # a buffer stamp further than this from now is not on our clock

    def __init__(self, url, context) -> None:
        import cv2

        config = V4L2Config.from_url(url)
        if not url.name:
            raise url.error("give the video device, e.g. v4l2:///dev/video0")
        self.url = url
        self.config = config
        self.device = url.name
        self.width, self.height, self.fps = config.width, config.height, config.fps
        self.fourcc, self.queue_len = config.fourcc, config.queue
        # the capture factory is injected so the driver's logic can be tested without hardware; the clock is
        # the run's (V4L2 buffer stamps are CLOCK_MONOTONIC, the host clock's default)
        self._factory = context.options.get("v4l2_capture", _opencv_capture)
        self._clock = context.clock_ns
        self._cv2 = cv2
        self._frames: queue.Queue[Frame] = queue.Queue(maxsize=max(1, self.queue_len))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._state = HealthState.DISCONNECTED
        self._detail = ""
        self._last_t_ns = 0
        self._last_arrival_ns = 0
        self._seq = 0
        self.nominal_fps: float | None = self.fps
        self.stats = {"frames": 0, "dropped_by_driver": 0, "dropped_by_consumer": 0, "reconnects": 0,
                      "unplugs": 0, "stamped_on_arrival": 0, "non_increasing_stamps": 0}

    @property
    def faults(self) -> collections.Counter[str]:
        return collections.Counter({k: v for k, v in self.stats.items() if k != "frames"})

    @classmethod
    def discover(cls) -> Discovery:
        found = video_devices()
        return Discovery("V4L2 video devices (frame grabbers)",
                         tuple(FoundDevice(d, f"v4l2://{d}?width=1920&height=1080&fps=60") for d in found),
                         "" if found else "no /dev/video* devices (is the grabber plugged in and its driver loaded?)")

    # --- opening and format negotiation ----------------------------------------------------------------------
    def _open_capture(self):
        cap = self._factory(self.device)
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            present = video_devices()
            raise DeviceNotFoundError(f"V4L2 device '{self.device}' cannot be opened (video devices here: "
                                      f"{', '.join(present) if present else 'none'})")
        cv2 = self._cv2
        if self.fourcc:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.fourcc))
        if self.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        if self.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.fps:
            cap.set(cv2.CAP_PROP_FPS, self.fps)
        got_w, got_h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        got_fps, got_cc = float(cap.get(cv2.CAP_PROP_FPS)), _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        wrong = []
        if self.width and got_w != self.width or self.height and got_h != self.height:
            wrong.append(f"size {got_w}x{got_h} (asked {self.width or got_w}x{self.height or got_h})")
        if self.fps and abs(got_fps - self.fps) > 0.01 * self.fps:
            wrong.append(f"{got_fps:g} fps (asked {self.fps:g})")
        if self.fourcc and got_cc != self.fourcc:
            wrong.append(f"format {got_cc} (asked {self.fourcc})")
        if wrong:
            cap.release()
            raise DeviceError(f"V4L2 device '{self.device}' does not support the requested mode: it gives "
                              f"{', '.join(wrong)}; pick a mode from 'v4l2-ctl -d {self.device} --list-formats-ext'")
        self.nominal_fps = got_fps or self.fps
        return cap

    def open(self) -> None:
        if self._thread is not None:
            return
        cap = self._open_capture()
        self._set_health(HealthState.OK, "")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(cap,), name=f"v4l2 {self.device}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._set_health(HealthState.DISCONNECTED, "closed")

    # --- the reader thread ---------------------------------------------------------------------------------------
    def _set_health(self, state: HealthState, detail: str) -> None:
        with self._lock:
            self._state, self._detail = state, detail

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
                    if failures >= self.failed_reads_for_unplug:
                        cap.release()
                        cap = None
                        self.stats["unplugs"] += 1
                        self._set_health(HealthState.DISCONNECTED, f"V4L2 device '{self.device}' stopped "
                                                                   f"delivering frames (unplugged?); reconnecting")
                        log.warning("V4L2 device '%s' lost; trying to reopen every %.1f s", self.device,
                                    self.reconnect_interval_s)
                    continue
                failures = 0
                self._deliver(image, cap.get(self._cv2.CAP_PROP_POS_MSEC))
            if cap is not None:
                cap.release()
        except BaseException as exc:  # surfaced by read(); never lost with the thread
            self._error = exc
            self._set_health(HealthState.FAULTED, f"reader thread failed: {exc}")

    def _reconnect(self):
        if self._stop.wait(self.reconnect_interval_s):
            return None
        try:
            cap = self._open_capture()
        except DeviceError:
            return None
        self.stats["reconnects"] += 1
        self._set_health(HealthState.OK, "reconnected")
        log.warning("V4L2 device '%s' reconnected", self.device)
        return cap

    def _stamp(self, pos_msec: float) -> int:
        now = self._clock()
        t_ns = int(round(pos_msec * 1e6)) if pos_msec and pos_msec > 0 else 0
        if t_ns == 0 or abs(now - t_ns) > self.clock_skew_limit_ns:
            self.stats["stamped_on_arrival"] += 1  # the driver's stamp is missing or on another clock
            t_ns = now
        if t_ns <= self._last_t_ns:
            self.stats["non_increasing_stamps"] += 1
            t_ns = self._last_t_ns + 1  # time never runs backwards for the consumer
        return t_ns

    def _deliver(self, image, pos_msec: float) -> None:
        t_ns = self._stamp(pos_msec)
        if self._last_t_ns and self.nominal_fps:
            period = 1e9 / self.nominal_fps
            gap = round((t_ns - self._last_t_ns) / period)
            if gap > 1:
                self.stats["dropped_by_driver"] += gap - 1
                self._seq += gap - 1  # sequence numbers keep their meaning: one per frame period
        self._last_t_ns = t_ns
        self._last_arrival_ns = self._clock()
        frame = Frame(image=image, t_ns=t_ns, seq=self._seq, host_ns=t_ns)  # (t_ns is on the monotonic clock)
        self._seq += 1
        self.stats["frames"] += 1
        try:
            self._frames.put_nowait(frame)
        except queue.Full:
            try:
                self._frames.get_nowait()  # the consumer is behind: the oldest frame goes
                self.stats["dropped_by_consumer"] += 1
            except queue.Empty:
                pass
            self._frames.put_nowait(frame)
        if self._state is not HealthState.OK:
            self._set_health(HealthState.OK, "")

    # --- the consumer's side ----------------------------------------------------------------------------------
    def read(self, timeout_s: float | None = None) -> Frame | None:
        if self._error is not None:
            raise DeviceError(f"V4L2 device '{self.device}': reader failed: {self._error}") from self._error
        if self._thread is None:
            raise DeviceError(f"V4L2 device '{self.device}' is not open")
        try:
            return self._frames.get(timeout=timeout_s)
        except queue.Empty:
            raise DeviceTimeoutError(f"V4L2 device '{self.device}': no frame within {timeout_s} s "
                                     f"({self.health.state.value}: {self.health.detail or 'no detail'})") from None

    @property
    def health(self) -> Health:
        with self._lock:
            state, detail = self._state, self._detail
        now = self._clock()
        if state is HealthState.OK and self._last_arrival_ns and self.nominal_fps and \
                now - self._last_arrival_ns > 3e9 / self.nominal_fps:
            state, detail = HealthState.STALE, f"no frame for {(now - self._last_arrival_ns) * 1e-6:.0f} ms"
        return Health(state, detail, now)
