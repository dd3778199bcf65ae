import numpy as np
import pytest

from lapreco_hil.errors import ConfigError
from lapreco_hil.geometry import interpolate_pose, make_T, rot_x
from lapreco_hil.kinematics import CameraKinematics, PoseAtTime
from lapreco_hil.robot_models import urdf_path
from lapreco_hil.types import JointSample


def mdh(alpha, a, theta, d):
    """Craig's modified DH: RotX(alpha) TransX(a) RotZ(theta) TransZ(d)."""
    ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
    return np.array([[ct, -st, 0, a], [st * ca, ct * ca, -sa, -sa * d], [st * sa, ct * sa, ca, ca * d], [0, 0, 0, 1]])


def ecm_fk_by_hand(q):
    """The ECM's published DH table (device-facts.md), multiplied out."""
    return (mdh(np.pi / 2, 0, q[0] + np.pi / 2, 0) @ mdh(-np.pi / 2, 0, q[1] - np.pi / 2, 0)
            @ mdh(np.pi / 2, 0, 0, q[2] - 0.3822) @ mdh(0, 0, q[3], 0.3829))


HAND_EYE = make_T(rot_x(np.deg2rad(30)), [0.0, -0.0015, 0.0])


@pytest.fixture(scope="module")
def kin():
    return CameraKinematics(str(urdf_path("ecm")), "ecm_tip", HAND_EYE)


def test_urdf_matches_the_dh_table(kin, rng):
    for _ in range(20):
        q = rng.uniform(kin.info.limits.lower, kin.info.limits.upper)
        np.testing.assert_allclose(kin.tip_pose(q), ecm_fk_by_hand(q), atol=1e-9)
        np.testing.assert_allclose(kin.camera_pose(q), ecm_fk_by_hand(q) @ HAND_EYE, atol=1e-9)


def test_joint_names_and_limits_come_from_the_urdf(kin):
    assert kin.info.joint_names == ("yaw", "pitch", "insertion", "roll")
    assert kin.info.limits.upper[2] == pytest.approx(0.255)
    assert kin.info.limits.lower[1] == pytest.approx(np.deg2rad(-44))


def test_insertion_moves_the_tip_along_the_shaft(kin):
    q = np.array([0.1, 0.2, 0.05, 0.3])
    T0 = kin.tip_pose(q)
    T1 = kin.tip_pose(q + [0, 0, 0.02, 0])
    np.testing.assert_allclose(T1[:3, 3] - T0[:3, 3], 0.02 * T0[:3, 2], atol=1e-12)


def test_rcm_rotation_error_is_leveraged_by_insertion(kin):
    """The seed's leverage argument: the same yaw/pitch error moves a deeper camera further."""
    sigma = np.array([0.003, 0.003, 0.0, 0.0])
    shallow = kin.camera_covariance([0, 0, 0.03, 0], sigma, 0.0, 0.0)
    deep = kin.camera_covariance([0, 0, 0.20, 0], sigma, 0.0, 0.0)
    assert np.trace(deep[3:, 3:]) > 20 * np.trace(shallow[3:, 3:])
    np.testing.assert_allclose(np.trace(deep[:3, :3]), np.trace(shallow[:3, :3]), rtol=1e-9)


def test_pose_at_time_interpolates_between_samples(kin):
    pa = PoseAtTime(kin, (0.003, 0.003, 0.0003, 0.003), 1e-4, 1e-4)
    qa, qb = np.array([0.0, 0.0, 0.1, 0.0]), np.array([0.02, -0.01, 0.11, 0.03])
    pa.add(JointSample(qa, 1_000, 0))
    pa.add(JointSample(qb, 3_000, 1))
    pa.add(JointSample(qa, 2_000, 2))  # out of order: ignored, time never runs backwards
    prior = pa.prior_at(1_500)
    expect = interpolate_pose(kin.camera_pose(qa), kin.camera_pose(qb), 0.25)
    np.testing.assert_allclose(prior.T_world_camera, expect, atol=1e-12)
    assert prior.cov.shape == (6, 6) and np.all(np.linalg.eigvalsh(prior.cov) > 0)


def test_bad_urdf_and_missing_frame_are_clear_errors(tmp_path):
    bad = tmp_path / "robot.urdf"
    bad.write_text("<robot name='x'><link name='a'/>")
    with pytest.raises(ConfigError, match="robot.urdf"):
        CameraKinematics(str(bad), "a", np.eye(4))
    with pytest.raises(ConfigError, match="no frame 'nope'"):
        CameraKinematics(str(urdf_path("ecm")), "nope", np.eye(4))
    with pytest.raises(ConfigError, match="no such URDF"):
        urdf_path("not-a-robot")


def test_pose_at_time_gives_no_pose_outside_or_between_distant_readings(kin):
    """A pose is interpolated only between two readings around the time, no further apart than
    MAX_GAP_PERIODS median periods: before the first, after the last and inside a long gap there is none
    (never the nearest reading held)."""
    from lapreco_hil.geometry import AFTER_LAST, BEFORE_FIRST, IN_GAP, MAX_GAP_PERIODS
    from lapreco_hil.kinematics import NoPoseError

    pa = PoseAtTime(kin, (0.003, 0.003, 0.0003, 0.003), 1e-4, 1e-4)
    with pytest.raises(NoPoseError, match="no joint readings received yet") as err:
        pa.prior_at(0)
    assert err.value.cause == BEFORE_FIRST
    q = np.array([0.0, 0.0, 0.1, 0.0])
    period = 10_000_000
    times = [i * period for i in range(10)] + [(9 + MAX_GAP_PERIODS + 1) * period + i * period for i in range(10)]
    for i, t in enumerate(times):
        pa.add(JointSample(q + 0.001 * i, int(t), i))
    assert pa.max_gap_ns == pytest.approx(MAX_GAP_PERIODS * period)
    assert pa.no_pose_cause(5 * period + 1) is None and pa.no_pose_cause(0) is None  # bracketed; on a reading
    assert pa.no_pose_cause(-1) == BEFORE_FIRST
    assert pa.no_pose_cause(int(times[-1]) + 1) == AFTER_LAST
    assert pa.no_pose_cause(11 * period) == IN_GAP
    for t, cause, words in ((-1, BEFORE_FIRST, "before the first joint reading"),
                            (int(times[-1]) + 1, AFTER_LAST, "after the last joint reading"),
                            (11 * period, IN_GAP, "gap between joint readings longer than 30.0 ms")):
        with pytest.raises(NoPoseError, match=words) as err:
            pa.prior_at(t)
        assert err.value.cause == cause
    # the offset moves video time onto kinematics time
    pa.offset_ns = -period
    assert pa.no_pose_cause(0) == BEFORE_FIRST and pa.no_pose_cause(int(times[-1]) + period) is None
