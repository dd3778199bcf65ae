"""close() while the polled robot driver's reader thread reconnects (drivers/robot/polling.py): a _connect that
outlasts close()'s wait for the reader must not leave the transport open with nobody to close it, nor the driver
marked connected after close."""

from __future__ import annotations

import threading
import time

import numpy as np

from lapreco_hil.drivers.robot.joint_map import dynamixel_joint_map
from lapreco_hil.drivers.robot.polling import PolledRobotConfig, PollingRobotDriver
from lapreco_hil.errors import DeviceDisconnectedError
from lapreco_hil.registry import DeviceContext, parse_url

from test_robot_drivers import wait_for


class SlowReconnectRobot(PollingRobotDriver):
    """A back-end whose link drops after a few readings and whose reconnect takes ``connect_s``."""

    reconnect_interval_s = 0.05
    close_join_s = 0.2

    def __init__(self, connect_s: float = 0.0, fail_after: int = 5) -> None:
        url = parse_url("fake://bus?rate=100")
        super().__init__(url, DeviceContext(), PolledRobotConfig.from_url(url), dynamixel_joint_map("ecm"), "fake bus")
        self.connect_s, self.fail_after = connect_s, fail_after
        self.open_transports = 0  # connects minus disconnects
        self.connects = 0
        self.connecting = threading.Event()
        self._polls = 0

    def _connect(self) -> None:
        self.connects += 1
        if self.connects > 1:  # a reconnect: slow
            self.connecting.set()
            time.sleep(self.connect_s)
        self.open_transports += 1

    def _disconnect(self) -> None:
        self.open_transports -= 1

    def _poll(self) -> tuple[np.ndarray, int]:
        self._polls += 1
        if self._polls == self.fail_after:
            raise DeviceDisconnectedError("fake bus: lost")
        return np.full(4, 2048, np.int64), time.monotonic_ns()


def test_close_during_a_reconnect_that_outlasts_it_disconnects_what_the_reconnect_opened():
    robot = SlowReconnectRobot(connect_s=0.6)
    robot.open()
    reader = robot._thread
    assert robot.connecting.wait(2.0)  # the reader is inside its slow _connect
    t0 = time.monotonic()
    robot.close()
    assert time.monotonic() - t0 < 0.5  # close() waits close_join_s, not the whole reconnect
    reader.join(timeout=2.0)
    assert not reader.is_alive()
    assert robot.open_transports == 0 and not robot._connected
    assert robot.faults["reconnects"] == 0


def test_close_waiting_out_a_reconnect_disconnects_once():
    robot = SlowReconnectRobot(connect_s=0.05)
    robot.close_join_s = 2.0
    robot.open()
    assert robot.connecting.wait(2.0)
    robot.close()
    assert robot.open_transports == 0 and not robot._connected and robot._thread is None


def test_a_reader_close_gave_up_on_is_waited_for_by_the_next_open():
    robot = SlowReconnectRobot(connect_s=0.4)
    robot.open()
    assert robot.connecting.wait(2.0)
    robot.close()  # gives up after 0.2 s
    robot.connect_s, robot.fail_after = 0.0, 10**9
    robot.open()  # waits for the old reader first: it must not come back to life
    try:
        assert robot.read(timeout_s=1.0)
        wait_for(lambda: robot.open_transports == 1, 1.0)
    finally:
        robot.close()
    assert robot.open_transports == 0
