"""What every device declares (robots and grabbers alike), what discovery reports, and the optional
capabilities some sources have (typing Protocols: check them with ``isinstance``)."""

from __future__ import annotations

import abc
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Protocol, runtime_checkable

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


@runtime_checkable
class FiniteSource(Protocol):
    """A source that knows how many items it will deliver (a session replay)."""

    def __len__(self) -> int:
        ...


@runtime_checkable
class RecordedSource(Protocol):
    """A source that plays a recorded session (``replay://``): the session itself is at hand."""

    session: Any
