"""What every device declares (robots and grabbers alike), what discovery reports, and the optional
capabilities some sources have (typing Protocols: check them with ``isinstance``)."""

from __future__ import annotations

import abc
import logging
import threading
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Mapping, Protocol, TypeVar, runtime_checkable

from lapreco_hil.drivers.health import Health
from lapreco_hil.errors import DeviceError

if TYPE_CHECKING:
    from lapreco_hil.registry import DeviceURL

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FoundDevice:
    address: str  # what the OS calls it: /dev/ttyUSB0, can0, /dev/video0, a scene name
    url: str  # a URL that opens it (with typical parameters)


@dataclass(frozen=True)
class Discovery:
    """What one back-end found on this machine; ``note`` says why nothing was found or what to check."""

    title: str
    found: tuple[FoundDevice, ...] = ()
    note: str = ""


class Device(abc.ABC):
    """Opened by URL through the registry; reports its health and counts its faults."""

    url: DeviceURL
    # the clock its stamps are on: "host" (real devices), "simulated", "recorded" (see lapreco_hil.registry)
    clock_domain: ClassVar[str] = "host"

    @abc.abstractmethod
    def open(self) -> None:
        """Connect; raises a DeviceError naming the device when it cannot."""

    @abc.abstractmethod
    def close(self) -> None:
        """Disconnect and stop any reader thread; safe to call twice."""

    @property
    @abc.abstractmethod
    def health(self) -> Health:
        ...

    @property
    def faults(self) -> Mapping[str, int]:
        """Counts per fault kind seen so far (a kind never seen reads 0); empty for a source without faults."""
        return Counter()

    @classmethod
    def discover(cls) -> Discovery | None:
        """The devices of this back-end present on this machine (None: the back-end cannot look)."""
        return None

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()



Sample = TypeVar("Sample")


class SampleStream(Device, Generic[Sample]):
    """A device that delivers timestamped samples (a robot's joint readings, a tracker's tool poses). A back-end
    implements ``_read``; ``read`` counts what it delivers (``readings_delivered``), so a caller can tell a device
    that delivered nothing from one whose every reading was refused (see ``faults``)."""

    _readings_delivered: int = 0

    @abc.abstractmethod
    def _read(self, timeout_s: float | None) -> list[Sample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""

    def read(self, timeout_s: float | None = None) -> list[Sample]:
        """Samples captured since the last call, oldest first (blocks up to ``timeout_s`` for at least one)."""
        samples = self._read(timeout_s)
        self._readings_delivered += len(samples)
        return samples

    @property
    def readings_delivered(self) -> int:
        """How many samples ``read`` has handed out since this object was made."""
        return self._readings_delivered

class ReaderHandover:
    """The hand-over between a threaded driver's ``close()`` and its reader thread, for a reader that close() cannot
    wait for (a reconnect or bring-up step that waits on the device): under ``_life``, whether the reader still
    runs and whether close() gave up on it. Whichever ends last ends the session, so a transport is never left open
    with nobody to close it. A driver calls ``_init_handover`` in its constructor, ``_wait_for_leftover`` and
    ``_reader_started`` in open(), ``_stop_reader`` in close(), and ends its reader under ``_life``."""

    close_join_s: float = 5.0
    device_name: str

    def _init_handover(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._life = threading.Lock()
        self._reader_running = False
        self._abandoned = False
        self._leftover: threading.Thread | None = None  # a reader close() left busy (open() waits for it)

    def _wait_for_leftover(self, doing: str) -> None:
        """open(): the last close() may have left its reader busy; it ends at its next step."""
        if self._leftover is not None:
            self._leftover.join(timeout=self.close_join_s)
            if self._leftover.is_alive():
                raise DeviceError(f"{self.device_name}: the previous session's reader thread is still busy "
                                  f"({doing}); try again")
            self._leftover = None

    def _reader_started(self, thread: threading.Thread) -> None:
        self._connected = True
        self._reader_running, self._abandoned = True, False
        self._thread = thread
        thread.start()

    def _stop_reader(self, left_to_it: str) -> bool:
        """close(): stop the reader and wait up to ``close_join_s``. True when a session was open and is the
        caller's to end; False when none was, or when the reader, still busy, ends it itself (``left_to_it``
        says how, in the warning)."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout=self.close_join_s)
        with self._life:
            if self._reader_running:
                self._abandoned = True
                self._leftover = thread
                log.warning("%s: the reader thread is still busy after %.1f s; it %s when it ends",
                            self.device_name, self.close_join_s, left_to_it)
                return False
            connected, self._connected = self._connected, False
        return connected


@runtime_checkable
class FiniteSource(Protocol):
    """A source that knows how many items it will deliver (a session replay)."""

    def __len__(self) -> int:
        ...


@runtime_checkable
class RecordedSource(Protocol):
    """A source that plays a recorded session (``replay://``): the session itself is at hand."""

    session: Any
