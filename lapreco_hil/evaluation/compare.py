"""The seed paper's comparison on one session: the Warp tracker and the OpenCV tracker, each with and without
the drift check, replayed on identical input; inliers (its Fig 3), tracking time per frame (Fig 5), ICP RMS
error against the true surface (Fig 6b), and camera pose error before and after bundle adjustment."""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path

import numpy as np

from ..outputs import prepare_output_dir

log = logging.getLogger(__name__)

VARIANTS = (("warp", True), ("warp", False), ("opencv", True), ("opencv", False))
SEED_FIGURES = {  # Moll, Tang, Van Gool: Fig 3 (inliers, skull sequence) and Fig 6b (ICP RMS, mm, skull)
    ("warp", False): {"name": "GPU", "inliers_skull": 4945, "inliers_uterus": 7865, "icp_rms_mm": 4.79},
    ("warp", True): {"name": "GPU drift corr.", "inliers_skull": 5138, "inliers_uterus": 8658, "icp_rms_mm": 2.20},
    ("opencv", False): {"name": "OpenCV", "inliers_skull": 7309, "inliers_uterus": 17542, "icp_rms_mm": 5.52},
    ("opencv", True): {"name": "OpenCV drift corr.", "inliers_skull": 16217, "inliers_uterus": 21894,
                       "icp_rms_mm": 1.96},
}


def variant_name(tracker: str, drift: bool) -> str:
    return f"{tracker}{'-drift' if drift else ''}"


def read_points_ply(path: Path) -> np.ndarray:
    import pyvista as pv

    if path.stat().st_size < 200 and "element vertex 0" in path.read_text(errors="ignore"):
        return np.zeros((0, 3))
    return np.asarray(pv.read(str(path)).points, float)


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from ..geometry import pose_from_tum

    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    t = np.array([float(r[0]) for r in rows])
    return t, np.array([pose_from_tum(r[1:8]) for r in rows]).reshape(-1, 4, 4)


def frame_timings(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in (rows[0].keys() if rows else [])}


def run_comparison(session: str, out: str, device: str = "auto", config_path: str | None = None,
                   variants=VARIANTS, progress: bool = True) -> dict:
    from ..cli.replay import run_replay
    from ..sessions import Session
    from .icp import evaluate_points

    out_dir = prepare_output_dir(out)
    truth = Session(session).ground_truth()
    rows = []
    for tracker, drift in variants:
        name = variant_name(tracker, drift)
        log.info("compare: %s", name)
        report = run_replay(session, str(out_dir / name), tracker=tracker, device=device, config_path=config_path,
                            drift_check=drift, progress=progress)
        times = frame_timings(out_dir / name / "frame_timings.csv")
        row = {"variant": name, "tracker": tracker, "drift_check": drift, "inliers": report["inliers"],
               "outliers": report["outliers"], "tracking_ms_mean": float(np.mean(times["frontend_ms"])),
               "tracking_ms_p95": float(np.percentile(times["frontend_ms"], 95)),
               "tracking_ms_per_frame": times["frontend_ms"].tolist(), "device": report["device"]}
        acc = report.get("accuracy", {})
        if "camera_raw_fk" in acc:
            row["camera_raw_mm"] = acc["camera_raw_fk"]["position_rms_mm"]
            row["camera_refined_mm"] = acc["camera_refined"]["position_rms_mm"]
        if truth is not None and truth.surface is not None:
            cam = report["camera"]
            _, poses = read_tum(out_dir / name / "trajectory.tum")
            ev = evaluate_points(read_points_ply(out_dir / name / "points.ply"), truth.surface, poses,
                                 np.array(cam["K"]), (cam["width"], cam["height"]))
            row["icp_rms_mm"] = ev.get("icp", {}).get("rms_mm")
            row["icp_scale"] = ev.get("icp", {}).get("scale")
            row["coverage"] = ev.get("coverage", {}).get("covered_fraction")
        rows.append(row)
    result = {"session": str(session), "variants": rows,
              "seed": {variant_name(*k): v for k, v in SEED_FIGURES.items()}}
    (out_dir / "comparison.json").write_text(json.dumps(result, indent=2))
    (out_dir / "comparison.md").write_text(format_markdown(result))
    plot_tracking_times(result, out_dir / "tracking_time.png")
    return result


def _f(v, fmt: str = "{:.2f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def format_markdown(result: dict) -> str:
    lines = [f"Session: `{result['session']}`", "",
             "| variant | inliers (Fig 3) | seed: skull / uterus | tracking ms/frame mean / p95 (Fig 5) "
             "| ICP RMS mm (Fig 6b) | seed: skull | ICP scale | coverage | camera mm raw -> refined |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in result["variants"]:
        seed = result["seed"][r["variant"]]
        lines.append(
            f"| {seed['name']} (`{r['variant']}`) | {r['inliers']} | {seed['inliers_skull']} / {seed['inliers_uterus']} | "
            f"{r['tracking_ms_mean']:.1f} / {r['tracking_ms_p95']:.1f} | {_f(r.get('icp_rms_mm'))} | "
            f"{seed['icp_rms_mm']:.2f} | {_f(r.get('icp_scale'), '{:.4f}')} | {_f(r.get('coverage'), '{:.0%}')} | "
            f"{_f(r.get('camera_raw_mm'), '{:.3f}')} -> {_f(r.get('camera_refined_mm'), '{:.3f}')} |")
    return "\n".join(lines) + "\n"


def plot_tracking_times(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4), dpi=100)
    for r in result["variants"]:
        ax.plot(r["tracking_ms_per_frame"], label=f"{result['seed'][r['variant']]['name']} ({r['device']})",
                linewidth=1)
    ax.set_xlabel("frame")
    ax.set_ylabel("tracking time (ms)")
    ax.set_title("Tracking time per frame (cf. the seed's Fig 5)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
