"""NDI port status bit 7 (0x80, "partially out of volume"; bit 6, 0x40, is "out of volume"): a pose partially out of
the characterised volume is out of it for the app (``in_volume`` False: delivered, recorded with in_volume 0,
refused as a camera pose), counted in ``out_of_volume`` and on its own in ``partially_out_of_volume`` (which the
probe shows), and named in the tracker's health."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lapreco_hil.drivers.health import HealthState
from lapreco_hil.errors import ConfigError
from lapreco_hil.drivers.tracker.ndi_protocol import (HANDLE_VALID, PORT_OUT_OF_VOLUME, PORT_PARTIALLY_OUT_OF_VOLUME,
                                                      parse_bx, parse_tx)
from lapreco_hil.registry import DeviceContext, open_tracker
from lapreco_hil.simulators.ndi_emulator import PARTIAL, NDITrackerEmulator

from test_ndi_tracker import FAST, bx_reply, moving_pose, served_error, wait_for


@pytest.mark.parametrize("status, inside, partial", [(0x31, True, False), (0x31 | 0x40, False, False),
                                                     (0x31 | 0x80, False, True), (0x31 | 0xC0, False, False)])
def test_both_volume_bits_decode_from_bx_and_tx(status, inside, partial):
    assert (PORT_OUT_OF_VOLUME, PORT_PARTIALLY_OUT_OF_VOLUME) == (0x40, 0x80)
    q, t = (1.0, 0.0, 0.0, 0.0), (1.0, 2.0, -1500.0)
    (rec,) = parse_bx(bx_reply([(0x0A, HANDLE_VALID, (*q, *t, 0.1), status, 7)])).records
    text = "01" + "0A" + "+10000+00000+00000+00000+000100+000200-150000+01000" + f"{status:08X}{7:08X}\n" + "0000"
    (rec_tx,) = parse_tx(text).records
    for r in (rec, rec_tx):
        assert r.port_status == status
        assert r.in_volume is inside and r.partially_out_of_volume is partial


def partial_chain() -> NDITrackerEmulator:
    """Two wired tools: handle 0A inside the volume, 0B partially out of it."""
    return NDITrackerEmulator(wired=[moving_pose(np.zeros(3)),
                                     moving_pose(np.array([50.0, 0, 0]), in_volume=lambda t: PARTIAL)])


@pytest.mark.parametrize("reply", ["bx", "tx"])
def test_partially_out_poses_are_flagged_counted_and_degrade_health(reply):
    tol_m = 1e-6 if reply == "bx" else 9e-6
    with partial_chain() as emu:
        with open_tracker(f"ndi://{emu.port}?rate=40&reply={reply}&{FAST}", DeviceContext()) as tracker:
            tracker.read(timeout_s=1.0)
            wait_for(lambda: tracker.faults["partially_out_of_volume"] >= 5)
            health = tracker.health
            time.sleep(0.1)
            samples = tracker.read()
            faults = tracker.faults
    partly = [s for s in samples if s.tool == "handle 0B"]
    assert partly and not any(s.in_volume for s in partly)  # still poses, not trusted ones
    assert all(s.in_volume for s in samples if s.tool == "handle 0A")
    for s in partly:  # the pose itself is the device's
        dt, dr = served_error(emu, 0x0B, s.T_tracker_marker)
        assert dt < tol_m and dr < 3e-4, (dt, dr)
    # every partially-out pose is an out-of-volume one too (as the session's in_volume 0 row is on replay)
    assert faults["out_of_volume"] == faults["partially_out_of_volume"], faults
    assert health.state is HealthState.DEGRADED and "handle 0B: partially out of volume" in health.detail, health


def test_the_probe_shows_partially_out_poses():
    from lapreco_hil.app.devices import probe

    with partial_chain() as emu:
        text = probe(f"ndi://{emu.port}?rate=60&{FAST}", 1.0, device="cpu")
    lines = text.splitlines()
    rows = {" ".join(line.split()[:2]): line.split() for line in lines if line.startswith("  handle")}
    assert int(rows["handle 0A"][8]) == 0  # outside-volume column
    assert int(rows["handle 0B"][8]) == int(rows["handle 0B"][2]) > 20
    assert "partially_out_of_volume" in lines[-1], lines[-1]


def test_partially_out_poses_are_recorded_with_in_volume_0_and_refused_as_camera_poses(tmp_path):
    from lapreco_hil.camera import CameraModel
    from lapreco_hil.pose_sources import MarkerPoseSource
    from lapreco_hil.sessions import SessionMeta, SessionWriter
    from lapreco_hil.sessions import format as fmt

    with partial_chain() as emu:
        with open_tracker(f"ndi://{emu.port}?rate=60&{FAST}", DeviceContext()) as tracker:
            tracker.read(timeout_s=1.0)
            time.sleep(0.3)
            samples = tracker.read(timeout_s=1.0)
    assert {s.tool for s in samples} == {"handle 0A", "handle 0B"}
    camera = CameraModel(64, 48, 50.0, 51.0, 31.5, 23.5, (0.1, -0.02), 22.0)
    meta = SessionMeta(camera=camera, pose_source="marker_poses", length_unit="mm",
                       tracker=fmt.TrackerSetup("handle 0B", np.eye(4)))
    with SessionWriter(tmp_path / "s", meta) as writer:
        assert writer.add_marker_samples(samples) == 0
    table, _ = fmt.read_marker_table(tmp_path / "s" / fmt.MARKER_POSES_FILE, 1e-3)
    inside = dict.fromkeys(table.tools)
    for tool, flag in zip(table.tools, table.in_volume):
        inside[tool] = (inside[tool] or set()) | {bool(flag)}
    assert inside == {"handle 0A": {True}, "handle 0B": {False}}
    # the pose source takes none of the partially-out scope poses: each refused as out of the volume
    n = sum(t == "handle 0B" for t in table.tools)
    with pytest.raises(ConfigError, match=f"no usable pose of the scope's tool 'handle 0B' .*\\({n} out_of_volume\\)"):
        MarkerPoseSource(fmt.TrackerSetup("handle 0B", np.eye(4)), table=table)
    assert len(MarkerPoseSource(fmt.TrackerSetup("handle 0A", np.eye(4)), table=table).track) > 0

