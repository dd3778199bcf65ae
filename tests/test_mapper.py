"""Keyframe selection: robot motion, track loss, and parallax with the camera rotation removed."""

import numpy as np

from lapreco_hil.config import MapperConfig
from lapreco_hil.geometry import Rotation, make_T
from lapreco_hil.mapping.mapper import Mapper
from lapreco_hil.types import Observations, PosePrior

K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
COV = np.diag([1e-6] * 3 + [1e-8] * 3)


def obs(seq, ids, uv):
    return Observations(seq, seq * 40_000_000, np.asarray(ids), np.asarray(uv, float),
                        np.zeros((len(ids), 3), np.uint8))


def project(T, X):
    Tc = np.linalg.inv(T)
    Xc = X @ Tc[:3, :3].T + Tc[:3, 3]
    return Xc[:, :2] / Xc[:, 2:] * 450.0 + [320, 240]


def mapper():
    # robot-motion triggers off, so only track loss and parallax decide
    return Mapper(K, MapperConfig(keyframe_translation_m=1.0, keyframe_rotation_rad=1.0, keyframe_parallax_deg=1.0))


def test_track_loss_makes_a_keyframe(rng):
    m = mapper()
    X = np.column_stack([rng.uniform(-0.03, 0.03, (100, 2)), np.full(100, 0.1)])
    T = np.eye(4)
    uv = project(T, X)
    assert m.add(obs(0, np.arange(100), uv), PosePrior(T, COV, 0))
    assert not m.add(obs(1, np.arange(100), uv), PosePrior(T, COV, 1))
    assert m.add(obs(2, np.arange(50), uv[:50]), PosePrior(T, COV, 2))  # half the tracks lost


def test_parallax_not_rotation_makes_a_keyframe(rng):
    m = mapper()
    X = np.column_stack([rng.uniform(-0.03, 0.03, (100, 2)), rng.uniform(0.08, 0.12, 100)])
    T0 = np.eye(4)
    m.add(obs(0, np.arange(100), project(T0, X)), PosePrior(T0, COV, 0))
    turned = make_T(Rotation.from_rotvec([0, 0.05, 0]).as_matrix(), [0, 0, 0])  # 3 degrees, no baseline
    assert not m.add(obs(1, np.arange(100), project(turned, X)), PosePrior(turned, COV, 1))
    moved = make_T(np.eye(3), [0.004, 0, 0])  # 4 mm at 100 mm: about 2.3 degrees of parallax
    assert m.add(obs(2, np.arange(100), project(moved, X)), PosePrior(moved, COV, 2))
