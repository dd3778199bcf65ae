"""The simulated endoscope holder: a smooth scan about the RCM, joint compliance and encoder readings.

Truth is the *link* side: the scope really is at FK(q_link). The encoders sit on the motors, so the robot
reports q_motor = q_link - deflection, quantised, with encoder noise. The deflection is what makes FK of the
reported joints miss the true camera pose by a small rotation about the RCM, which the long scope turns into
millimetres at the tip (the seed's reason for bundle adjustment). The ECM is gravity-balanced, so the
deflection is modelled as zero-mean: slow elastic wander (cable stretch, gear elasticity: an
Ornstein-Uhlenbeck process) plus direction-dependent backlash.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScanTrajectory:
    """Lissajous scan about the home pose: yaw, pitch, insertion, roll (rad, rad, m, rad)."""

    home: tuple[float, float, float, float] = (0.0, 0.0, 0.10, 0.0)
    amplitude: tuple[float, float, float, float] = (0.14, 0.10, 0.012, 0.09)
    period_s: float = 8.0
    # relative frequencies and phases of the four joints
    harmonics: tuple[float, float, float, float] = (1.0, 1.5, 0.5, 0.75)
    phases: tuple[float, float, float, float] = (0.0, 0.7, 0.0, 1.1)

    def q(self, t_s: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)[..., None]
        w = 2 * np.pi * np.asarray(self.harmonics) / self.period_s
        return np.asarray(self.home) + np.asarray(self.amplitude) * np.sin(w * t + np.asarray(self.phases))

    def qdot(self, t_s: float | np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)[..., None]
        w = 2 * np.pi * np.asarray(self.harmonics) / self.period_s
        return np.asarray(self.amplitude) * w * np.cos(w * t + np.asarray(self.phases))


@dataclass(frozen=True)
class ComplianceModel:
    """Per-joint deflection: OU wander (sigma, time constant) + backlash b * tanh(qdot / v0)."""

    sigma: tuple[float, ...] = (0.0030, 0.0030, 0.00025, 0.0025)
    tau_s: float = 0.15
    backlash: tuple[float, ...] = (0.0015, 0.0015, 0.0001, 0.0010)
    backlash_velocity: tuple[float, ...] = (0.01, 0.01, 0.001, 0.01)
    encoder_resolution: tuple[float, ...] = (2 * np.pi / 65536, 2 * np.pi / 65536, 1e-6, 2 * np.pi / 65536)
    encoder_noise: tuple[float, ...] = (2 * np.pi / 65536, 2 * np.pi / 65536, 1e-6, 2 * np.pi / 65536)


class JointDeflection:
    """Deterministic (seeded) deflection time series, extended on demand in fixed chunks so the values at a
    time do not depend on the order in which times are asked for."""

    DT = 0.001
    CHUNK = 4096

    def __init__(self, model: ComplianceModel, trajectory: ScanTrajectory, seed: int) -> None:
        self.model = model
        self.trajectory = trajectory
        self._rng = np.random.default_rng(seed)
        self._ou = np.zeros((1, len(model.sigma)))

    def _ensure(self, n: int) -> None:
        a = np.exp(-self.DT / self.model.tau_s)
        s = np.asarray(self.model.sigma) * np.sqrt(1 - a * a)
        while self._ou.shape[0] <= n:
            noise = self._rng.standard_normal((self.CHUNK, self._ou.shape[1])) * s
            chunk = np.empty_like(noise)
            x = self._ou[-1] if self._ou.shape[0] > 1 else self._rng.standard_normal(noise.shape[1]) * np.asarray(
                self.model.sigma)
            for i in range(self.CHUNK):
                x = a * x + noise[i]
                chunk[i] = x
            self._ou = np.vstack([self._ou, chunk])

    def at(self, t_s: float) -> np.ndarray:
        k = t_s / self.DT
        i = int(np.floor(k))
        self._ensure(i + 2)
        f = k - i
        ou = (1 - f) * self._ou[i + 1] + f * self._ou[i + 2]
        m = self.model
        lash = np.asarray(m.backlash) * np.tanh(self.trajectory.qdot(t_s) / np.asarray(m.backlash_velocity))
        return ou + lash


class SimulatedArm:
    """Joint truth and encoder readings of the simulated holder."""

    def __init__(self, trajectory: ScanTrajectory, compliance: ComplianceModel, seed: int) -> None:
        self.trajectory = trajectory
        self.compliance = compliance
        self.deflection = JointDeflection(compliance, trajectory, seed)
        self._seed = seed

    def true_joints(self, t_s: float) -> np.ndarray:
        return self.trajectory.q(t_s)

    def motor_joints(self, t_s: float) -> np.ndarray:
        """Encoder-side joint positions at t (the link side minus compliance), before quantisation: what a
        device emulator turns into its own encoder counts."""
        return self.true_joints(t_s) - self.deflection.at(t_s)

    def reported_joints(self, t_s: float, seq: int) -> np.ndarray:
        """What the encoders read at t: motor side, quantised, with noise (seeded by the sample number)."""
        c = self.compliance
        q_motor = self.motor_joints(t_s)
        rng = np.random.default_rng((self._seed, seq))
        q = q_motor + rng.standard_normal(q_motor.shape) * np.asarray(c.encoder_noise)
        res = np.asarray(c.encoder_resolution)
        return np.round(q / res) * res
