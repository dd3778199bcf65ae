"""The seed paper's comparison (run by lapreco_hil.app.compare): its variants and figures, the readers of a
run's outputs, the table and the tracking-time plot. The seed ran its Warp-like tracker on a GPU; a variant is
labelled by the device it actually ran on."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


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


def variant_label(tracker: str, drift: bool, device: str) -> str:
    """What ran, on what: 'Warp on GPU (cuda:0) drift corr.', 'Warp on CPU', 'OpenCV drift corr.'."""
    if tracker == "warp":
        name = f"Warp on {'GPU' if device.startswith('cuda') else 'CPU'} ({device})"
    else:
        name = "OpenCV"
    return name + (" drift corr." if drift else "")


def read_report_camera(cam: dict):
    """The camera a run's report.json records (``camera``: size, K, distortion, field of view) as a CameraModel."""
    from lapreco_hil.camera import CameraModel, FieldOfView

    K = np.asarray(cam["K"], float)
    fov = cam.get("fov")
    return CameraModel(int(cam["width"]), int(cam["height"]), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                       tuple(cam.get("dist") or ()), float(cam.get("fov_radius_px") or 0.0),
                       FieldOfView(**fov) if fov else None)


def read_points_ply(path: Path) -> np.ndarray:
    import pyvista as pv

    if path.stat().st_size < 200 and "element vertex 0" in path.read_text(errors="ignore"):
        return np.zeros((0, 3))
    return np.asarray(pv.read(str(path)).points, float)


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from lapreco_hil.geometry import pose_from_tum

    rows = [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    t = np.array([float(r[0]) for r in rows])
    return t, np.array([pose_from_tum(r[1:8]) for r in rows]).reshape(-1, 4, 4)


def frame_timings(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in (rows[0].keys() if rows else [])}


def _f(v, fmt: str = "{:.2f}") -> str:
    return "n/a" if v is None else fmt.format(v)


def format_markdown(result: dict) -> str:
    lines = [f"Session: `{result['session']}`", "",
             "| variant (ran on) | inliers (Fig 3) | seed: skull / uterus | tracking ms/frame mean / p95 (Fig 5) "
             "| rigid ICP RMS mm (Fig 6b) | seed: skull | similarity ICP scale | coverage | camera mm raw -> refined "
             "| coverage 1 mm sparse / dense | dense RMS mm |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["variants"]:
        seed = result["seed"][r["variant"]]
        lines.append(
            f"| {variant_label(r['tracker'], r['drift_check'], r['device'])} (`{r['variant']}`; seed: {seed['name']}) | {r['inliers']} | {seed['inliers_skull']} / {seed['inliers_uterus']} | "
            f"{r['tracking_ms_mean']:.1f} / {r['tracking_ms_p95']:.1f} | {_f(r.get('icp_rms_mm'))} | "
            f"{seed['icp_rms_mm']:.2f} | {_f(r.get('icp_scale'), '{:.4f}')} | {_f(r.get('coverage'), '{:.0%}')} | "
            f"{_f(r.get('camera_raw_mm'), '{:.3f}')} -> {_f(r.get('camera_refined_mm'), '{:.3f}')} | "
            f"{_f(r.get('coverage_1mm_sparse'), '{:.0%}')} / {_f(r.get('coverage_1mm_dense'), '{:.0%}')} | "
            f"{_f(r.get('dense_rms_mm'))} |")
    return "\n".join(lines) + "\n"


def plot_tracking_times(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4), dpi=100)
    for r in result["variants"]:
        ax.plot(r["tracking_ms_per_frame"], label=variant_label(r["tracker"], r["drift_check"], r["device"]),
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
