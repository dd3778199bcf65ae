"""Raw encoder counts <-> joint positions in SI units, per joint:
``q = sign * (counts - zero_count) * si_per_count + offset``.

Each device's own convention for where zero is (what a map gives when nothing overrides it):

- ROBOTIS Dynamixel X-series (Protocol 2.0, Present Position, address 132, 4 bytes, 4096 ticks per
  revolution): the position range of Position Control Mode is 0..4095 ticks and its centre, **2048 ticks, is
  0 rad** (0.0879 deg = 2*pi/4096 rad per tick). Servos assembled at their centre read about 2048 at the
  joint's zero; a chain resting near 2048 is at rest near 0 rad. Prismatic joints driven by a Dynamixel
  follow the same rule: 2048 ticks = 0 m, ``lead_m`` per revolution.
- CiA 402 drives (CANopen, 0x6064 position actual value, increments): **0 increments = 0** (rad or m), the
  drive's own home position, unless the map says otherwise.

The driver and its device emulator build their map the same way (``dynamixel_joint_map``,
``cia402_joint_map``), as canopen's LocalNode and RemoteNode share one object dictionary. A map comes from the
robot model (revolute joints: radians, prismatic: metres) plus the encoder's counts per revolution and, for
prismatic joints, the lead (metres per revolution); a TOML file (``map=FILE`` in the device URL) overrides
sign, zero, offset and scale per joint::

    [[joint]]
    name = "pitch"
    sign = -1
    zero_count = 2048        # counts at which the joint reads ``offset`` (default: the device's convention)
    offset = 0.0123          # rad (or m): the joint position at ``zero_count``
    counts_per_rev = 4096
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lapreco_hil.errors import ConfigError
from lapreco_hil.kinematics import prismatic_joints
from lapreco_hil.robot_models import urdf_path


@dataclass(frozen=True)
class JointMap:
    names: tuple[str, ...]
    si_per_count: np.ndarray  # rad or m per count
    sign: np.ndarray
    offset: np.ndarray
    lower: np.ndarray  # limits (SI), from the robot model
    upper: np.ndarray
    is_prismatic: np.ndarray  # (n,) bool
    zero_count: np.ndarray  # counts at which each joint reads ``offset``

    def to_si(self, counts) -> np.ndarray:
        return self.sign * (np.asarray(counts, np.float64) - self.zero_count) * self.si_per_count + self.offset

    def to_counts(self, q) -> np.ndarray:
        steps = (np.asarray(q, np.float64) - self.offset) / (self.sign * self.si_per_count)
        return (np.round(steps) + self.zero_count).astype(np.int64)

    def unit(self, i: int) -> str:
        return "m" if self.is_prismatic[i] else "rad"

    def beyond_limits(self, q: np.ndarray, margin_rad: float = 0.05, margin_m: float = 0.005) -> np.ndarray:
        """Per joint: beyond its limits (plus a margin for calibration slack), or not finite."""
        q = np.asarray(q, np.float64)
        margin = np.where(self.is_prismatic, margin_m, margin_rad)
        return (q < self.lower - margin) | (q > self.upper + margin) | ~np.isfinite(q)

    def out_of_limits(self, q: np.ndarray, margin_rad: float = 0.05, margin_m: float = 0.005) -> list[str]:
        """Descriptions of the joints beyond their limits (plus a margin for calibration slack)."""
        bad = self.beyond_limits(q, margin_rad, margin_m)
        return [f"joint '{self.names[i]}' = {q[i]:.4g} {self.unit(i)} outside [{self.lower[i]:.4g}, "
                f"{self.upper[i]:.4g}] {self.unit(i)}" for i in np.flatnonzero(bad)]

    @staticmethod
    def for_model(model: str, counts_per_rev: float = 4096, lead_m: float = 0.002,
                  overrides: str | Path | None = None, zero_count: int = 0) -> "JointMap":
        """The map of ``model``'s joints; ``zero_count`` is the device's zero convention (see the module)."""
        import pinocchio as pin

        path = urdf_path(model)
        try:
            m = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as exc:
            raise ConfigError(f"{path}: cannot load URDF ({str(exc).splitlines()[0]})") from None
        names = tuple(m.names[1:])
        prismatic = prismatic_joints(m)
        per_rev = np.full(len(names), float(counts_per_rev))
        sign = np.ones(len(names))
        offset = np.zeros(len(names))
        zero = np.full(len(names), float(zero_count))
        if overrides is not None:
            sign, offset, per_rev, zero = _read_overrides(Path(overrides), names, sign, offset, per_rev, zero)
        si_per_count = np.where(prismatic, lead_m, 2 * np.pi) / per_rev
        return JointMap(names, si_per_count, sign, offset, m.lowerPositionLimit.copy(), m.upperPositionLimit.copy(),
                        prismatic, zero)


DYNAMIXEL_CENTRE_TICKS = 2048  # Dynamixel X-series: the centre of the 0..4095 position range is 0 rad
DYNAMIXEL_TICKS_PER_REV = 4096
CIA402_ZERO = 0  # CiA 402: position actual value 0 is the joint's zero


def dynamixel_joint_map(model: str = "ecm", overrides: str | Path | None = None, lead_m: float = 0.002,
                        counts_per_rev: float = DYNAMIXEL_TICKS_PER_REV) -> JointMap:
    """The map of a Dynamixel X-series chain: 2048 ticks = 0 rad (0 m), 4096 ticks per revolution."""
    return JointMap.for_model(model, counts_per_rev, lead_m, overrides, zero_count=DYNAMIXEL_CENTRE_TICKS)


def cia402_joint_map(model: str = "ecm", overrides: str | Path | None = None, lead_m: float = 0.002,
                     counts_per_rev: float = 4 * 4096) -> JointMap:
    """The map of CiA 402 drives: 0 increments = 0; default 4 x 4096 increments per revolution (quadrature)."""
    return JointMap.for_model(model, counts_per_rev, lead_m, overrides, zero_count=CIA402_ZERO)


def _read_overrides(path: Path, names, sign, offset, per_rev, zero):
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read joint map ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    sign, offset, per_rev, zero = sign.copy(), offset.copy(), per_rev.copy(), zero.copy()
    for n, entry in enumerate(data.get("joint", [])):
        if not isinstance(entry, dict) or entry.get("name") not in names:
            raise ConfigError(f"{path}: [[joint]] #{n + 1} must name one of {', '.join(names)}")
        i = names.index(entry["name"])
        for key in entry:
            if key not in ("name", "sign", "offset", "counts_per_rev", "zero_count"):
                raise ConfigError(f"{path}: [[joint]] '{entry['name']}': unknown key '{key}' (known: sign, "
                                  f"zero_count, offset, counts_per_rev)")
        s = entry.get("sign", 1)
        if s not in (1, -1):
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': sign must be 1 or -1")
        cpr = entry.get("counts_per_rev", per_rev[i])
        if not isinstance(cpr, (int, float)) or cpr <= 0:
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': counts_per_rev must be positive")
        off = entry.get("offset", 0.0)
        if not isinstance(off, (int, float)):
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': offset must be a number")
        z = entry.get("zero_count", zero[i])
        if isinstance(z, bool) or not isinstance(z, (int, float)):
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': zero_count must be a number of counts")
        sign[i], offset[i], per_rev[i], zero[i] = s, float(off), float(cpr), float(z)
    return sign, offset, per_rev, zero
