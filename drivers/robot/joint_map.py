"""Raw encoder counts <-> joint positions in SI units, per joint: ``q = sign * counts * si_per_count + offset``.

The driver and the device emulator share one JointMap, as canopen's LocalNode and RemoteNode share one
object dictionary. A map comes from the robot model (revolute joints: radians, prismatic: metres) plus the
encoder's counts per revolution and, for prismatic joints, the lead (metres per revolution); a TOML file
(``map=FILE`` in the device URL) overrides sign, offset and scale per joint::

    [[joint]]
    name = "pitch"
    sign = -1
    offset = 0.0123          # rad (or m): the joint position at zero counts
    counts_per_rev = 4096
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ConfigError
from ...kinematics import prismatic_joints
from ...robot_models import urdf_path


@dataclass(frozen=True)
class JointMap:
    names: tuple[str, ...]
    si_per_count: np.ndarray  # rad or m per count
    sign: np.ndarray
    offset: np.ndarray
    lower: np.ndarray  # limits (SI), from the robot model
    upper: np.ndarray
    is_prismatic: np.ndarray  # (n,) bool

    def to_si(self, counts) -> np.ndarray:
        return self.sign * np.asarray(counts, np.float64) * self.si_per_count + self.offset

    def to_counts(self, q) -> np.ndarray:
        return np.round((np.asarray(q, np.float64) - self.offset) / (self.sign * self.si_per_count)).astype(np.int64)

    def out_of_limits(self, q: np.ndarray, margin_rad: float = 0.05, margin_m: float = 0.005) -> list[str]:
        """Descriptions of the joints beyond their limits (plus a margin for calibration slack)."""
        margin = np.where(self.is_prismatic, margin_m, margin_rad)
        bad = (q < self.lower - margin) | (q > self.upper + margin) | ~np.isfinite(q)
        return [f"joint '{self.names[i]}' = {q[i]:.4g} outside [{self.lower[i]:.4g}, {self.upper[i]:.4g}]"
                for i in np.flatnonzero(bad)]

    @staticmethod
    def from_url(url, counts_per_rev: float) -> "JointMap":
        """The map a device URL asks for: ``model=`` (default ecm), ``counts_per_rev=``, ``lead_m=``, ``map=``."""
        return JointMap.for_model(url.get("model", "ecm"), url.get("counts_per_rev", counts_per_rev, float),
                                  url.get("lead_m", 0.002, float), url.get("map", None))

    @staticmethod
    def for_model(model: str, counts_per_rev: float = 4096, lead_m: float = 0.002,
                  overrides: str | Path | None = None) -> "JointMap":
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
        if overrides is not None:
            sign, offset, per_rev = _read_overrides(Path(overrides), names, sign, offset, per_rev)
        si_per_count = np.where(prismatic, lead_m, 2 * np.pi) / per_rev
        return JointMap(names, si_per_count, sign, offset, m.lowerPositionLimit.copy(), m.upperPositionLimit.copy(),
                        prismatic)


def _read_overrides(path: Path, names, sign, offset, per_rev):
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read joint map ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    sign, offset, per_rev = sign.copy(), offset.copy(), per_rev.copy()
    for n, entry in enumerate(data.get("joint", [])):
        if not isinstance(entry, dict) or entry.get("name") not in names:
            raise ConfigError(f"{path}: [[joint]] #{n + 1} must name one of {', '.join(names)}")
        i = names.index(entry["name"])
        for key in entry:
            if key not in ("name", "sign", "offset", "counts_per_rev"):
                raise ConfigError(f"{path}: [[joint]] '{entry['name']}': unknown key '{key}'")
        s = entry.get("sign", 1)
        if s not in (1, -1):
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': sign must be 1 or -1")
        cpr = entry.get("counts_per_rev", per_rev[i])
        if not isinstance(cpr, (int, float)) or cpr <= 0:
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': counts_per_rev must be positive")
        off = entry.get("offset", 0.0)
        if not isinstance(off, (int, float)):
            raise ConfigError(f"{path}: [[joint]] '{entry['name']}': offset must be a number")
        sign[i], offset[i], per_rev[i] = s, float(off), float(cpr)
    return sign, offset, per_rev
