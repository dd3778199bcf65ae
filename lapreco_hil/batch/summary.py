"""The table and plots across a batch's sessions: summary.csv (every field of a row), summary.md (the columns a
reader compares) and PNG plots, written into the batch's output folder."""

from __future__ import annotations

import csv
import os
from pathlib import Path

from lapreco_hil.batch.rows import SessionRow
from lapreco_hil.errors import OutputError

CSV_FILE = "summary.csv"
MARKDOWN_FILE = "summary.md"
QUALITY_PLOT = "inliers_rms.png"
LATENCY_PLOT = "latency.png"

# (header, row field, format) of summary.md
MARKDOWN_COLUMNS = (
    ("session", "session", "{}"), ("status", "status", "{}"), ("frames", "frames", "{}"),
    ("inliers", "inliers", "{}"), ("RMS mm", "rms_mm", "{:.2f}"), ("coverage", "coverage", "{:.0%}"),
    ("camera error mm", "camera_mm", "{:.3f}"), ("fps", "fps", "{:.1f}"),
    ("latency p50 ms", "latency_p50_ms", "{:.1f}"), ("latency p99 ms", "latency_p99_ms", "{:.1f}"),
    ("wall s", "wall_s", "{:.1f}"), ("error", "error", "{}"),
)


def write_summary(rows: list[SessionRow], out_dir: Path, title: str) -> dict[str, Path]:
    """summary.csv, summary.md and the plots; returns their paths by kind."""
    paths = {"csv": out_dir / CSV_FILE, "markdown": out_dir / MARKDOWN_FILE,
             "quality_plot": out_dir / QUALITY_PLOT, "latency_plot": out_dir / LATENCY_PLOT}
    try:
        _write_atomic(paths["csv"], _csv_text(rows))
        _write_atomic(paths["markdown"], format_markdown(rows, title))
        plot_quality(rows, paths["quality_plot"])
        plot_latency(rows, paths["latency_plot"])
    except OSError as exc:
        raise OutputError(f"cannot write the batch summary in '{out_dir}' ({exc.strerror}); choose another --out") \
            from None
    return paths


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _csv_text(rows: list[SessionRow]) -> str:
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=SessionRow.columns(), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _csv_cell(v) for k, v in row.as_dict().items()})
    return buf.getvalue()


def _csv_cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _cell(row: SessionRow, field: str, fmt: str) -> str:
    value = getattr(row, field)
    if value is None or value == "":
        return ""
    if field == "status" and row.earlier:
        return f"{value} (earlier run)"
    return fmt.format(value).replace("|", "\\|")


def format_markdown(rows: list[SessionRow], title: str) -> str:
    ok = sum(r.status == "ok" for r in rows)
    lines = [f"# {title}", "",
             f"{len(rows)} sessions: {ok} ok, {len(rows) - ok} failed. RMS: inlier points to the true surface; "
             "coverage: share of the visible true surface within 3 mm of a point (after similarity ICP) or the "
             "run's own; camera error: camera position RMS after bundle adjustment; latency: frame received -> "
             "pose and points updated; wall: replay and evaluation of the session.", "",
             "| " + " | ".join(h for h, _, _ in MARKDOWN_COLUMNS) + " |",
             "|" + "|".join("---" for _ in MARKDOWN_COLUMNS) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row, f, fmt) for _, f, fmt in MARKDOWN_COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def _bars(ax, names: list[str], values: list, color: str, ylabel: str, failed: list[bool]) -> None:
    x = range(len(names))
    ax.bar(x, [0.0 if v is None else v for v in values], color=color)
    for i, (v, bad) in enumerate(zip(values, failed)):
        if bad:
            ax.annotate("failed", (i, 0), ha="center", va="bottom", color="red", fontsize=8, rotation=90)
        elif v is None:
            ax.annotate("n/a", (i, 0), ha="center", va="bottom", color="grey", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_xticks(list(x))
    ax.set_xticklabels(names, rotation=45, ha="right", fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)


def _width(rows: list[SessionRow]) -> float:
    return min(24.0, max(6.0, 0.5 * len(rows) + 2.0))


def plot_quality(rows: list[SessionRow], path: Path) -> None:
    """Inlier points and their RMS to the true surface, per session."""
    from matplotlib.figure import Figure

    names, failed = [r.session for r in rows], [r.status != "ok" for r in rows]
    fig = Figure(figsize=(_width(rows), 6), dpi=100)
    top, bottom = fig.subplots(2, 1, sharex=True)
    _bars(top, names, [r.inliers for r in rows], "tab:blue", "inlier points", failed)
    top.set_title("Inliers and accuracy per session")
    _bars(bottom, names, [r.rms_mm for r in rows], "tab:orange", "RMS to true surface (mm)", failed)
    fig.tight_layout()
    fig.savefig(path)


def plot_latency(rows: list[SessionRow], path: Path) -> None:
    """Latency p50 and p99 per session (ms)."""
    from matplotlib.figure import Figure

    names, failed = [r.session for r in rows], [r.status != "ok" for r in rows]
    fig = Figure(figsize=(_width(rows), 4), dpi=100)
    ax = fig.subplots()
    x = list(range(len(rows)))
    ax.bar([i - 0.2 for i in x], [r.latency_p50_ms or 0.0 for r in rows], width=0.4, label="p50", color="tab:green")
    ax.bar([i + 0.2 for i in x], [r.latency_p99_ms or 0.0 for r in rows], width=0.4, label="p99", color="tab:red")
    for i, bad in enumerate(failed):
        if bad:
            ax.annotate("failed", (i, 0), ha="center", va="bottom", color="red", fontsize=8, rotation=90)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("latency (ms)")
    ax.set_title("Frame latency per session: received -> pose and points updated")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
