"""The sessions of a batch and their rows. A session's outputs go to OUT/<session name>/ (the outputs contract
of DESIGN.md); ``batch.json`` is written there last, atomically, by a finished replay and evaluation, so a
folder with it is done and a resumed batch reads its row back instead of replaying it again."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from lapreco_hil.errors import ConfigError
from lapreco_hil.sessions.format import META_FILE

DONE_FILE = "batch.json"  # written last by a finished session; its absence means "not done"
REPORT_FILE = "report.json"


@dataclass(frozen=True)
class SessionRow:
    """One session's figures (None: not known, e.g. no ground truth); ``status`` is 'ok' or 'failed'."""

    session: str
    status: str
    earlier: bool = False  # read back from an earlier run's outputs (resumed), not replayed by this one
    frames: int | None = None  # frames processed
    frames_in: int | None = None
    inliers: int | None = None
    rms_mm: float | None = None  # inlier points to the true surface, RMS (no alignment)
    icp_rms_mm: float | None = None  # after rigid ICP, scale 1 (lapreco evaluate)
    coverage: float | None = None  # share of the visible true surface covered (0..1)
    camera_raw_mm: float | None = None  # camera position RMS of the raw pose source
    camera_mm: float | None = None  # camera position RMS after bundle adjustment
    fps: float | None = None
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    wall_s: float | None = None  # replay + evaluation, as the task measured it
    cpu_s: float | None = None  # the task's CPU time (its process's, all threads)
    tracker: str | None = None
    device: str | None = None
    host: str | None = None
    error: str = ""

    @classmethod
    def columns(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def as_dict(self) -> dict:
        return asdict(self)


def find_sessions(sessions_dir: str | Path) -> tuple[list[Path], list[Path]]:
    """(sessions, other folders) directly under ``sessions_dir``, sorted by name: a session is a folder with a
    session.json. A missing folder, or one with no session, is a one-line error."""
    root = Path(sessions_dir)
    if not root.is_dir():
        raise ConfigError(f"sessions folder '{root}' does not exist; give the folder that holds the session "
                          f"folders (each with a {META_FILE})")
    if (root / META_FILE).is_file():
        raise ConfigError(f"'{root}' is one session; give the folder that holds sessions (or run lapreco replay "
                          f"{root} --out DIR)")
    sessions, others = [], []
    for child in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        (sessions if (child / META_FILE).is_file() else others).append(child)
    if not sessions:
        raise ConfigError(f"sessions folder '{root}' holds no session (no sub-folder with a {META_FILE}); record "
                          f"some with lapreco record or lapreco sim-record --out {root}/NAME")
    return sessions, others


def is_done(out_dir: Path) -> bool:
    """A finished run's outputs: its done file says ok and its report.json is there."""
    try:
        done = json.loads((out_dir / DONE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return done.get("status") == "ok" and (out_dir / REPORT_FILE).is_file()


def failed_row(session: str, error: str, wall_s: float | None = None, host: str | None = None,
               cpu_s: float | None = None) -> SessionRow:
    # one line: a multi-line message would break the table
    line = " ".join(str(error).split())
    return SessionRow(session=session, status="failed", error=line, wall_s=wall_s, cpu_s=cpu_s, host=host)


def _get(doc: dict | None, *keys):
    for key in keys:
        if not isinstance(doc, dict):
            return None
        doc = doc.get(key)
    return doc


def _coverage(report: dict, evaluation: dict | None) -> float | None:
    """The report's own coverage (a dense surface may write one, as a fraction or a dict with
    covered_fraction), else the evaluation's."""
    for found in (report.get("coverage"), _get(report, "dense", "coverage")):
        if isinstance(found, (int, float)) and not isinstance(found, bool):
            return float(found)
        if isinstance(found, dict) and isinstance(found.get("covered_fraction"), (int, float)):
            return float(found["covered_fraction"])
    return _get(evaluation, "coverage", "covered_fraction")


def row_from_outputs(session: str, out_dir: Path, earlier: bool = False) -> SessionRow:
    """The row of a done session, from its report.json and done file."""
    report = json.loads((out_dir / REPORT_FILE).read_text(encoding="utf-8"))
    done = json.loads((out_dir / DONE_FILE).read_text(encoding="utf-8"))
    evaluation = done.get("evaluation")
    acc = report.get("accuracy") or {}
    return SessionRow(
        session=session, status="ok", earlier=earlier,
        frames=_get(report, "frames", "processed"), frames_in=_get(report, "frames", "in"),
        inliers=report.get("inliers"),
        rms_mm=_get(acc, "points_to_surface", "rms_mm"),
        icp_rms_mm=_get(evaluation, "icp", "rms_mm"),
        coverage=_coverage(report, evaluation),
        camera_raw_mm=_get(acc, "camera_raw_fk", "position_rms_mm"),
        camera_mm=_get(acc, "camera_refined", "position_rms_mm"),
        fps=report.get("throughput_fps"),
        latency_p50_ms=_get(report, "latency_ms", "p50"), latency_p99_ms=_get(report, "latency_ms", "p99"),
        wall_s=done.get("wall_s", report.get("wall_s")), cpu_s=done.get("cpu_s"),
        tracker=report.get("tracker"), device=report.get("device"), host=done.get("host"),
        # a replay that worked but could not be evaluated (e.g. fewer than 3 points) says so here
        error=done.get("evaluation_error") or "",
    )
