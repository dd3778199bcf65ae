"""``lapreco emulate``: the command runs in a subprocess, prints the pty to connect to and the driver URL, and this
repository's own drivers read it from this process; Ctrl-C (or SIGTERM) ends it cleanly. CANopen: the missing
SocketCAN interface and the refused virtual bus are one-line errors; on python-can's virtual bus (in this
process) the app's emulator is read by the CANopen driver."""

from __future__ import annotations

import itertools
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from lapreco_hil.errors import DeviceNotFoundError
from lapreco_hil.registry import DeviceContext, open_robot, open_tracker

REPO = Path(__file__).resolve().parents[1]
FAST = "reset_wait_ms=100&timeout_ms=300"
_channels = itertools.count()


class Emulate:
    """``lapreco emulate ...`` in a subprocess; ``info`` holds its ``key: value`` lines up to 'Ctrl-C to stop'."""

    def __init__(self, *args: str, timeout_s: float = 60.0) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "lapreco_hil.cli.main", "emulate", *args], cwd=REPO,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.info: dict[str, str] = {}
        self.lines: list[str] = []
        head: queue.Queue[str | None] = queue.Queue()

        def read_head() -> None:  # the lines up to 'Ctrl-C to stop'; the rest is left for communicate()
            for line in iter(self.proc.stdout.readline, ""):
                head.put(line.rstrip("\n"))
                if line.startswith("Ctrl-C to stop"):
                    return
            head.put(None)

        reader = threading.Thread(target=read_head, daemon=True)
        reader.start()
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                line = head.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                self.stop(signal.SIGKILL)
                raise AssertionError(f"no 'Ctrl-C to stop' within {timeout_s} s: {self.lines}") from None
            if line is None:
                raise AssertionError(f"lapreco emulate ended: {self.lines} {self.proc.stderr.read()}")
            self.lines.append(line)
            if line == "Ctrl-C to stop":
                reader.join()
                return
            key, sep, value = line.partition(": ")
            if sep:
                self.info.setdefault(key, value)

    def stop(self, sig=signal.SIGINT) -> tuple[int, str, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=20)
        return self.proc.returncode, out, err

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        if self.proc.poll() is None:
            self.stop(signal.SIGKILL)


def test_emulate_dynamixel_prints_the_pty_and_url_and_the_driver_reads_it():
    from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map

    with Emulate("dynamixel", "--ids", "1-4", "--baud", "57600", "--motion", "still") as emu:
        port, url = emu.info["port"], emu.info["url"]
        assert os.path.realpath(port).startswith("/dev/pts/")  # the stable name of a real pty
        assert url == f"serial://{port}?baud=57600&ids=1,2,3,4&model=ecm"
        with open_robot(url + "&rate=50", DeviceContext()) as robot:
            samples = robot.read(timeout_s=3.0)
            raw = robot.take_raw_readings()
        # the same chain at the driver's default rate: not understood (a real chain at 57600 would not be)
        with pytest.raises(DeviceNotFoundError, match="at 1000000 baud: no servo answered .*check the baud rate"):
            open_robot(url.replace("baud=57600", "baud=1000000"), DeviceContext()).open()
        rc, out, err = emu.stop()
    assert rc == 0 and "stopped" in out, (rc, out, err)
    assert not os.path.lexists(port)  # closed: the name is gone
    jm = dynamixel_joint_map("ecm")
    middle = (jm.lower + jm.upper) / 2  # still: every joint at the middle of its limits
    assert raw and all(r.delivered for r in raw)
    assert samples
    np.testing.assert_allclose(samples[-1].q, middle, atol=2 * np.max(jm.si_per_count))


def test_emulate_ndi_serves_one_session_after_another_and_ends_on_sigterm():
    with Emulate("ndi", "--wired", "2", "--frame-rate", "40") as emu:
        url = emu.info["url"]
        assert url == f"ndi://{emu.info['port']}?baud=921600&rate=40"
        for _ in range(2):  # a probe, then a record: the same emulator, two bring-ups
            with open_tracker(f"{url}&{FAST}", DeviceContext()) as tracker:
                assert tracker.tools == ("handle 0A", "handle 0B")
                samples = tracker.read(timeout_s=2.0)
            assert samples and {s.tool for s in samples} <= {"handle 0A", "handle 0B"}
            assert all(abs(s.T_tracker_marker[2, 3] + 1.2) < 0.05 for s in samples)  # 1.2 m in front, metres
        rc, out, _ = emu.stop(signal.SIGTERM)
    assert rc == 0 and "stopped" in out


def test_emulate_canopen_without_the_socketcan_interface_is_one_line():
    channel = "lapreco-nocan"
    if (Path("/sys/class/net") / channel).exists():
        pytest.skip(f"this machine has a CAN interface named {channel}")
    result = subprocess.run([sys.executable, "-m", "lapreco_hil.cli.main", "emulate", "canopen", "--interface",
                             "socketcan", "--channel", channel], cwd=REPO, capture_output=True, text=True,
                            timeout=60)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"lapreco: error: SocketCAN interface '{channel}' does not exist on this machine")
    assert f"ip link add dev {channel} type vcan" in lines[0] and result.stdout == ""


def test_emulate_canopen_refuses_the_virtual_bus_and_says_why():
    result = subprocess.run([sys.executable, "-m", "lapreco_hil.cli.main", "emulate", "canopen", "--interface",
                             "virtual"], cwd=REPO, capture_output=True, text=True, timeout=60)
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "inside one process only" in lines[0] and "--interface socketcan --channel vcan0" in lines[0]


def test_the_app_s_canopen_emulator_on_the_virtual_bus_is_read_by_the_driver():
    from lapreco_hil.app.emulate import start_canopen

    channel = f"emulate-{next(_channels)}"
    running = start_canopen(interface="virtual", channel=channel, motion="scan")
    try:
        assert running.url == f"canopen://virtual/{channel}?nodes=1,2,3,4&model=ecm"
        assert any("one process only" in line for line in running.lines)
        with open_robot(running.url + "&rate=100", DeviceContext()) as robot:
            robot.read(timeout_s=2.0)
            time.sleep(0.5)
            samples = robot.read(timeout_s=2.0)
    finally:
        running.close()
    assert len(samples) >= 10
    q = np.array([s.q for s in samples])
    info = robot.info
    assert np.all(q >= info.limits.lower) and np.all(q <= info.limits.upper)  # the scan stays within the limits
    assert np.ptp(q[:, 0]) > 0  # and moves


@pytest.mark.parametrize("argv, message", [
    (["dynamixel", "--baud", "12345"], "baud 12345 is not an X-series baud rate"),
    (["dynamixel", "--ids", "1,2,3"], "3 servo IDs for the 4 joints of model 'ecm'"),
    (["dynamixel", "--alert", "9"], "--alert 9: not one of the chain's IDs"),
    (["ndi", "--wired", "0"], "an NDI tracker with no tool"),
    (["ndi", "--start-baud", "4800"], "start baud 4800 is not an NDI rate"),
])
def test_bad_options_are_one_line(argv, message, capsys):
    from lapreco_hil.cli.main import main

    assert main(["emulate", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lapreco: error: ") and message in err and err.count("\n") == 1, err
