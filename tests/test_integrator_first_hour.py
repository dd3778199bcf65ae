"""A robot integrator's first recording, as issue 25 tried it: a Dynamixel X-series chain resting near its centre
(2048 ticks), recorded with the plain URL (no joint map given) through the `lapreco record` command. Every
reading the chain answered must land in the session, with the SI values the X-series convention gives
(computed here from the raw ticks, not from the project's JointMap)."""

from __future__ import annotations

import csv
import json

import numpy as np

from lapreco_hil.calib.files import write_handeye_yaml
from lapreco_hil.cli.main import main
from lapreco_hil.simulators.dynamixel_emulator import DynamixelChainEmulator

from test_joint_convention import TICKS, expected_si


def test_record_through_a_chain_resting_at_2048_keeps_every_reading(tmp_path, warp_cpu, capsys):
    hand_eye = tmp_path / "handeye.yaml"
    write_handeye_yaml(hand_eye, np.eye(4), robot_model="ecm", tip_frame="ecm_tip")
    out = tmp_path / "session"
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS) as emu:
        rc = main(["record", "--robot", f"serial://{emu.port}?ids=1,2,3,4",
                   "--grabber", "sim://skull?width=160&height=120&fps=10", "--frames", "10",
                   "--hand-eye", str(hand_eye), "--device", warp_cpu, "--out", str(out), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    meta = json.loads((out / "session.json").read_text())
    with open(out / "joints.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    delivered = meta["health"]["robot_readings_delivered"]
    assert len(rows) > 10 and len(rows) == delivered  # every reading the driver handed on is in the session
    assert "out_of_limits" not in meta["health"]["robot_faults"]
    names = [k for k in rows[0] if k not in ("t_ns", "seq")]
    q = np.array([[float(r[n]) for n in names] for r in rows])
    np.testing.assert_allclose(q, np.broadcast_to(expected_si(TICKS), q.shape), rtol=0, atol=1e-9)


def test_a_robot_model_other_than_the_drivers_is_refused_before_recording(tmp_path, warp_cpu, capsys):
    """The driver converts encoder counts by its URL's model (default ecm). A --robot-model whose insertion joint
    is revolute recorded the ecm's metres as radians, 3000x too small, with exit 0; it is refused, naming both
    models and the fix. The same model given twice passes."""
    from lapreco_hil.robot_models import urdf_path

    text = urdf_path("ecm").read_text()
    mine = tmp_path / "myrobot.urdf"
    mine.write_text(text.replace('<joint name="insertion" type="prismatic">', '<joint name="insertion" type="revolute">'))
    same = tmp_path / "ecm_copy.urdf"
    same.write_text(text)
    hand_eye = tmp_path / "handeye.yaml"
    write_handeye_yaml(hand_eye, np.eye(4))
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: TICKS) as emu:
        args = ["record", "--robot", f"serial://{emu.port}?ids=1,2,3,4", "--grabber",
                "sim://skull?width=160&height=120&fps=10", "--frames", "3", "--tip-frame", "ecm_tip",
                "--hand-eye", str(hand_eye), "--device", warp_cpu, "--no-progress"]
        rc = main(args + ["--robot-model", str(mine), "--out", str(tmp_path / "wrong")])
        err = capsys.readouterr().err
        assert rc == 2 and "insertion (rad)" in err and "insertion (m)" in err and f"model={mine}" in err, err
        assert not (tmp_path / "wrong").exists()
        assert main(args + ["--robot-model", str(same), "--out", str(tmp_path / "same")]) == 0


def test_a_live_run_whose_every_reading_the_driver_refuses_says_so(tmp_path, warp_cpu, capsys):
    """Readings beyond the model's limits are refused by the driver itself, before the pose source: the run's
    error blamed "the robot delivered no reading; check its URL and link" where the link was fine."""
    hand_eye = tmp_path / "handeye.yaml"
    write_handeye_yaml(hand_eye, np.eye(4), robot_model="ecm", tip_frame="ecm_tip")
    far = np.array(TICKS) + 4096 * 10  # ten turns off: beyond every revolute joint's limits
    with DynamixelChainEmulator([1, 2, 3, 4], ticks_at=lambda t_ns: far) as emu:
        rc = main(["run", "--robot", f"serial://{emu.port}?ids=1,2,3,4",
                   "--grabber", "sim://skull?width=160&height=120&fps=10", "--seconds", "3",
                   "--hand-eye", str(hand_eye), "--device", warp_cpu, "--tracker", "opencv",
                   "--out", str(tmp_path / "run"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0 and "driver refused" in err and "out of the model's joint limits" in err, err
    assert "delivered no reading" not in err
