"""An NDI tracker that resets in the middle of a session (a power blip: back at 9600 baud, neither initialised
nor tracking, its handles and uploaded .rom files gone) is brought up again by the driver: on the RESET it sends
unasked, or, when that never arrives readable, on replies lost in a row for about a second. Counted in faults,
health stale meanwhile (the port is fine: not disconnected), OK once poses come again; the passive tools' .rom
files are uploaded again and the poses after it are the served ones under the same tool names."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.registry import DeviceContext, open_tracker
from lapreco_hil.simulators.ndi_emulator import NDITrackerEmulator

from test_robot_drivers import wait_for

FAST = "reset_wait_ms=100&timeout_ms=300"


def moving_pose(offset_mm: np.ndarray):
    def pose_at(t_ns: int):
        s = t_ns * 1e-9
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("zyx", [0.7 * s, 0.3 * np.sin(s), 0.1]).as_matrix()
        T[:3, 3] = offset_mm + [30.0 * np.sin(s), 20.0 * np.cos(s), -1200.0]
        return T, True
    return pose_at


def served_error(emu: NDITrackerEmulator, handle: int, T_m: np.ndarray) -> float:
    """Translation (m) between a delivered pose and the nearest pose served for that handle."""
    return min((float(np.linalg.norm(T_mm[:3, 3] * 1e-3 - T_m[:3, 3]))
                for h, _f, T_mm, _iv in list(emu.served) if h == handle), default=np.inf)


class HealthLog:
    """The tracker's health (state, detail), sampled every few ms on a thread of its own; kept when the state or
    the detail's words change."""

    def __init__(self, tracker) -> None:
        self.tracker, self.seen, self._stop = tracker, [], threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            time.sleep(0.003)

    def _sample(self) -> None:
        h = self.tracker.health
        words = (h.state, re.sub(r"\d", "", h.detail))
        if not self.seen or (self.seen[-1][0], re.sub(r"\d", "", self.seen[-1][1])) != words:
            self.seen.append((h.state, h.detail))

    def stop(self) -> list:
        self._stop.set()
        self._thread.join()
        self._sample()
        return self.seen


@pytest.fixture
def roms(tmp_path):
    rng = np.random.default_rng(4)
    out = []
    for name, n in (("8700339", 150), ("8700340", 64)):
        path = tmp_path / f"{name}.rom"
        path.write_bytes(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        out.append(path)
    return out


@pytest.mark.parametrize("announce, reply", [(True, "bx"), (True, "tx"), (False, "bx"), (False, "tx")])
def test_a_tracker_reset_mid_session_is_brought_up_again(roms, announce, reply):
    with NDITrackerEmulator(passive=[moving_pose(np.zeros(3)), moving_pose(np.array([100.0, 0, 0]))]) as emu:
        url = f"ndi://{emu.port}?rate=60&reply={reply}&tools={roms[0]},{roms[1]}&{FAST}"
        with open_tracker(url, DeviceContext()) as tracker:
            assert tracker.read(timeout_s=1.0)
            wait_for(lambda: tracker.health.state is HealthState.OK, 2.0)
            pvwr, inits = emu.commands["PVWR"], emu.commands["INIT"]
            health = HealthLog(tracker)
            emu.power_blip(announce=announce)
            assert not emu.tracking and emu.baud == 9600 and all(t.wired for t in emu.handles.values())
            time.sleep(0.2)
            tracker.read()
            wait_for(lambda: tracker.faults["reconnects"] == 1, 6.0)
            after = tracker.read(timeout_s=1.0)
            wait_for(lambda: tracker.health.state is HealthState.OK, 2.0)
            seen = health.stop()
            faults = tracker.faults
        assert emu.tracking is False  # TSTOP on close, as after any session
    # the full bring-up again: INIT, COMM back to the session's rate, every .rom uploaded again (3 + 1 chunks)
    assert emu.commands["INIT"] == inits + 1 and emu.commands["PVWR"] == 2 * pvwr == 8
    assert emu.roms[1][:150] == roms[0].read_bytes() and emu.roms[2] == roms[1].read_bytes()
    if announce:  # the RESET on the line: at once, no wait for replies to be lost
        assert faults["device_resets"] == 1 and faults["unanswered"] == 0, faults
    else:  # nothing readable came: replies lost for about a second
        assert faults["unanswered"] == 1 and faults["device_resets"] == 0 and faults["timeouts"] >= 2, faults
    states = [s for s, _ in seen]
    assert HealthState.STALE in states and HealthState.DISCONNECTED not in states, seen
    assert states[-1] is HealthState.OK, seen
    stale = next(d for s, d in seen if s is HealthState.STALE and "bringing" in d)
    assert ("RESET" if announce else "replies lost in a row") in stale, stale
    # the poses after the reset are the served ones, under the same tool names
    assert after and {s.tool for s in after} <= {"8700339", "8700340"}
    for s in after:
        assert served_error(emu, 1 if s.tool == "8700339" else 2, s.T_tracker_marker) < 1e-5


def test_a_reset_whose_bring_up_fails_keeps_trying_and_stays_stale(roms):
    """A device that resets and then stays silent a while: the driver keeps trying (stale, never a dead thread)
    and takes it on once it answers."""
    with NDITrackerEmulator(passive=[moving_pose(np.zeros(3))]) as emu:
        with open_tracker(f"ndi://{emu.port}?rate=60&tools={roms[0]}&{FAST}", DeviceContext()) as tracker:
            assert tracker.read(timeout_s=1.0)
            emu.faults.silent = True
            emu.power_blip(announce=False)
            wait_for(lambda: tracker.faults["unanswered"] == 1, 3.0)
            time.sleep(1.5)  # a bring-up or two fail: no tracker answers
            health = tracker.health
            emu.faults.silent = False
            wait_for(lambda: tracker.faults["reconnects"] == 1, 6.0)
            tracker.read()
            assert tracker.read(timeout_s=1.0)
    assert health.state is HealthState.STALE and "no NDI tracker answers" in health.detail, health


# --- close() while the reader brings the tracker up again -------------------------------------------------------

def test_close_during_a_mid_session_bring_up_closes_the_port_and_leaves_the_tracker_stopped():
    """close() while the reader waits for the RESET after its break (up to reset_wait_ms): the bring-up stops at
    once, and neither the port nor a tracking device is left behind by a reader that outlived close()."""
    with NDITrackerEmulator(wired=[moving_pose(np.zeros(3))]) as emu:
        tracker = open_tracker(f"ndi://{emu.port}?rate=60&reset_wait_ms=6000&timeout_ms=300", DeviceContext())
        tracker.open()
        assert tracker.read(timeout_s=1.0)
        reader = tracker._thread
        emu.power_blip(announce=False)
        wait_for(lambda: tracker.faults["unanswered"] == 1, 5.0)
        time.sleep(0.5)  # the reader is inside the bring-up: the 6 s wait for RESET after its break
        t0 = time.monotonic()
        tracker.close()
        took = time.monotonic() - t0
        reader.join(timeout=8.0)
        time.sleep(0.3)
        assert took < 2.0, took
        assert not reader.is_alive() and not tracker._connected and tracker._ser is None
        assert not emu.tracking and emu.command_log[-1] != "TSTART", list(emu.command_log)[-5:]


def test_a_bring_up_that_completes_as_close_gives_up_on_it_ends_the_session_itself(roms):
    """The bring-up completes after close() stopped waiting for the reader: the reader ends the session (TSTOP,
    PHF of its passive tool's handle) and closes the port, instead of marking itself connected with nobody left
    to do it."""
    with NDITrackerEmulator(passive=[moving_pose(np.zeros(3))]) as emu:
        tracker = open_tracker(f"ndi://{emu.port}?rate=60&tools={roms[0]}&{FAST}", DeviceContext())
        tracker.open()
        assert tracker.read(timeout_s=1.0)
        reader = tracker._thread
        connect, completed = tracker._connect, threading.Event()

        def slow_connect(after_reset: bool = False) -> None:  # a device that takes its time (INIT, PINIT)
            connect(after_reset)
            completed.set()
            time.sleep(0.6)

        tracker._connect = slow_connect
        tracker.close_join_s = 0.2
        emu.power_blip(announce=True)
        assert completed.wait(5.0) and emu.tracking  # brought up again: tracking, the reader not yet back
        tracker.close()  # gives up on the reader after 0.2 s
        reader.join(timeout=3.0)
        assert not reader.is_alive()
        assert not emu.tracking and list(emu.command_log)[-2:] == ["TSTOP", "PHF"], list(emu.command_log)[-5:]
        assert [h for h, t in emu.handles.items() if not t.wired] == []
        assert not tracker._connected and tracker._ser is None and tracker.faults["reconnects"] == 0
