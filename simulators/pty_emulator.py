"""A device behind a pseudo-terminal, as the device emulators are: a stable name (a symlink to the pty's slave,
like /dev/ttyUSB0 or udev's by-id links) that a real driver opens with pyserial and cannot tell from a USB
adapter, a thread that serves the master side, and ``disconnect()`` / ``reconnect()`` (the adapter unplugged and
plugged back in: the name disappears, then points at a new pty).

A pty carries no line speed, but it keeps the one the driver set through termios: ``line_baud()`` reads it on the
slave side, so an emulator can ignore what a host sends at a rate other than the device's, as a UART would (the
bytes arrive as framing errors, never as a packet)."""

from __future__ import annotations

import abc
import fcntl
import os
import struct
import tempfile
import termios
import threading
import tty
from pathlib import Path

# termios speed constant -> baud (B9600 -> 9600, B1000000 -> 1000000, ...)
TERMIOS_RATES = {getattr(termios, n): int(n[1:]) for n in dir(termios) if n.startswith("B") and n[1:].isdigit()}
_TCGETS2 = 0x802C542A  # Linux x86/arm: _IOR('T', 0x2A, struct termios2), 44 bytes; c_ispeed at offset 36


def line_baud(fd: int) -> int | None:
    """The rate a driver set on the tty ``fd`` (either side of a pty): a standard termios rate, or one set with
    BOTHER through termios2 (pyserial's custom rates); None when neither can be read."""
    rate = TERMIOS_RATES.get(termios.tcgetattr(fd)[4])
    if rate is not None:
        return rate
    try:
        raw = fcntl.ioctl(fd, _TCGETS2, bytes(44))
    except OSError:
        return None
    ispeed = struct.unpack_from("I", raw, 36)[0]
    return ispeed or None


class PtyEmulator(abc.ABC):
    """Subclasses set up their device state, then call ``_open_pty()``; ``_serve(master)`` answers the driver
    until ``self._stop`` is set."""

    def __init__(self, link_dir: str | None, prefix: str, device_name: str, thread_name: str) -> None:
        self._dir = Path(link_dir or tempfile.mkdtemp(prefix=prefix))
        self.port = str(self._dir / device_name)
        self._thread_name = thread_name
        self._master = self._slave = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @abc.abstractmethod
    def _serve(self, master: int) -> None:
        """Answer the driver on ``master`` until ``self._stop`` is set."""

    def _open_pty(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        self._master, self._slave = master, slave
        tmp = self.port + ".tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.port)  # the stable name, re-pointed on reconnect like udev's by-id links
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, args=(master,), name=self._thread_name, daemon=True)
        self._thread.start()

    def _line_baud(self) -> int | None:
        """The rate the driver set on the pty (None: one that cannot be read). Raises OSError / termios.error
        once the pty is closed."""
        return line_baud(self._slave)

    def _close_pty(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def disconnect(self) -> None:
        """The adapter is unplugged: the device node disappears and the driver's port fails."""
        self._close_pty()
        if os.path.lexists(self.port):
            os.unlink(self.port)

    def reconnect(self) -> None:
        """Plugged back in: a new pty behind the same name (the device keeps its state)."""
        self._open_pty()

    def close(self) -> None:
        self.disconnect()
        try:
            self._dir.rmdir()
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
