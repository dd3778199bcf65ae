"""What every device declares (robots and grabbers alike), what discovery reports, and the optional
capabilities some sources have (typing Protocols: check them with ``isinstance``)."""

from __future__ import annotations

import abc
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Mapping, Protocol, TypeVar, runtime_checkable

from lapreco_hil.drivers.health import Health

if TYPE_CHECKING:
    from lapreco_hil.registry import DeviceURL


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

@runtime_checkable
class FiniteSource(Protocol):
    """A source that knows how many items it will deliver (a session replay)."""

    def __len__(self) -> int:
        ...


@runtime_checkable
class RecordedSource(Protocol):
    """A source that plays a recorded session (``replay://``): the session itself is at hand."""

    session: Any
