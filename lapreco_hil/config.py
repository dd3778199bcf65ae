"""Configuration: frozen dataclasses, loaded once from TOML and passed down (no global parameters).

A TOML file mirrors the dataclass tree: ``[tracker]``, ``[mapper]``, ``[surface]``... Every key is optional;
an unknown key or a value of the wrong type is a :class:`ConfigError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

from .errors import ConfigError


@dataclass(frozen=True)
class TrackerConfig:
    max_features: int = 800
    min_distance_px: float = 8.0
    quality_level: float = 0.01
    block_size: int = 7
    window_px: int = 21
    pyramid_levels: int = 3
    max_lk_error: float = 30.0
    fov_margin_px: float = 12.0
    # re-detect when fewer than this share of max_features is alive
    redetect_below: float = 0.9
    # log-domain high-pass against moving shading (0 = track raw intensities, as the seed's baseline did)
    shading_sigma_px: float = 6.0
    # no new features where the local mean grey level is below this (0-255)
    min_brightness: float = 20.0
    # Zinsser drift check: affine + gain/bias registration of each track's first patch
    drift_check: bool = True
    drift_patch_px: int = 13
    drift_max_residual: float = 0.75


@dataclass(frozen=True)
class PriorConfig:
    """Joint-space 1-sigma error of the robot's reported joints (compliance, backlash, encoder),
    mapped to a camera-pose covariance through the manipulator Jacobian, plus a floor for what the
    joints do not explain (hand-eye, scope bending)."""

    joint_sigma: tuple[float, ...] = (0.0035, 0.0035, 0.0003, 0.0035)  # rad, rad, m, rad
    floor_rot_sigma_rad: float = 0.0005
    floor_trans_sigma_m: float = 0.0002


@dataclass(frozen=True)
class MapperConfig:
    keyframe_translation_m: float = 0.002
    keyframe_rotation_rad: float = 0.02
    keyframe_track_ratio: float = 0.7
    keyframe_parallax_deg: float = 1.0
    min_parallax_deg: float = 2.0
    max_reprojection_px: float = 3.0
    window_keyframes: int = 8
    # the seed's robust schedule: Cauchy then Tukey, MAD scale re-estimated before each stage
    local_cauchy_iterations: int = 3
    local_tukey_iterations: int = 3
    final_cauchy_iterations: int = 15
    final_tukey_iterations: int = 15
    sigma_floor_px: float = 0.2
    # a landmark is an inlier with at least this many inlier observations, making up at least this share
    min_inlier_observations: int = 3
    min_inlier_fraction: float = 0.5
    final_global_ba: bool = True
    # bounded memory for long runs: past this many keyframes the oldest ``retire_batch`` are retired (their
    # landmarks labelled and frozen, their observations let go); 0 keeps every keyframe active
    active_keyframes: int = 400
    # a frame's pose is refined against at most this many of its landmarks, evenly spread (0 = all)
    resection_max_points: int = 400
    retire_batch: int = 100


@dataclass(frozen=True)
class SurfaceConfig:
    alpha_factor: float = 4.0  # alpha = factor x median nearest-neighbour distance
    render_width: int = 1024
    render_height: int = 768


@dataclass(frozen=True)
class RuntimeConfig:
    """The live runtime's queues and rates (lapreco_hil/runtime)."""

    capture_queue: int = 4  # frames between capture and tracking; the oldest is dropped when full
    # observation slots in shared memory between tracking and the mapper process: enough to hold the frames
    # that arrive during one local BA (about a second at 60 fps), which the mapper then catches up on cheaply
    mapper_slots: int = 128
    mapper_backlog_skip_ba: int = 2  # local BA is deferred while more frames than this wait for the mapper
    # local BA in a worker process of its own, on the newest window, while the mapper goes on mapping frames
    # ("on"), or run by the mapper between frames, deferred while frames wait ("off"). "auto": on with 4 or
    # more CPU cores; on 2 cores a third busy process took the time tracking needs (25 -> 22 fps at 384x288)
    ba_worker: str = "auto"
    max_tracks: int = 4096
    max_landmarks: int = 200_000
    surface_period_s: float = 2.0  # live mesh rebuild
    surface_max_points: int = 15_000  # the live mesh is built on at most this many points, evenly thinned
    view_period_s: float = 0.0  # live textured view to PNG (0 = off)
    record_queue: int = 64
    # the front-end reports a "partial view" while its tracks span less than this share of the view they
    # normally span (an instrument or blood over part of the scope's view)
    partial_view_below: float = 0.6


@dataclass(frozen=True)
class PipelineConfig:
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)


def _build(cls, data: dict, where: str, source: str):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    names = {f.name for f in dataclasses.fields(cls)}
    for key, value in data.items():
        if key not in names:
            raise ConfigError(f"{source}: unknown key '{where}{key}' (known: {', '.join(sorted(names))})")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: '{where}{key}' must be a table [{where}{key}]")
            kwargs[key] = _build(hint, value, f"{where}{key}.", source)
            continue
        kwargs[key] = _coerce(value, hint, f"{where}{key}", source)
    return cls(**kwargs)


def _coerce(value, hint, name: str, source: str):
    origin = typing.get_origin(hint)
    if origin is tuple:
        if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                  and math.isfinite(v) and v >= 0 for v in value):
            raise ConfigError(f"{source}: '{name}' must be a list of non-negative numbers, got {value!r}")
        return tuple(float(v) for v in value)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: '{name}' must be true or false, got {value!r}")
        return value
    # every number in the configuration is a count, a size, a rate or a threshold: finite and >= 0
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"{source}: '{name}' must be a non-negative integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise ConfigError(f"{source}: '{name}' must be a finite non-negative number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: '{name}' must be a string, got {value!r}")
        return value
    return value


def config_from_dict(data: dict, source: str = "<config>") -> PipelineConfig:
    return _build(PipelineConfig, data, "", source)


def load_config(path: str | Path | None) -> PipelineConfig:
    """Load a TOML configuration; ``None`` gives the defaults."""
    if path is None:
        return PipelineConfig()
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror}); check the path") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start}); save the config as UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc}); fix the file") from None
    return config_from_dict(data, str(path))
