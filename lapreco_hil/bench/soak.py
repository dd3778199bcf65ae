"""``lapreco bench soak`` (run by lapreco_hil.app.bench): the live runtime on the simulated world for a long time (30 minutes for
docs/reliability.md), sampling every few seconds the resident memory of the main and the mapper process,
the map's size, the frames in and mapped, and the latency of the frames done since the last sample. The
summary gives memory growth (a straight-line fit after the warm-up) and latency drift (first vs last
stretch)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np


def rss_mb(pid: int | str = "self") -> float | None:
    """Resident memory of a process in MB (Linux /proc; None elsewhere or once it has gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class Sampler:
    """Samples a LiveRun every ``period_s`` from its own thread."""

    def __init__(self, period_s: float, stream: str | None = None) -> None:
        self.period_s = period_s
        self.samples: list[dict] = []
        self.stream = stream  # each sample is also appended here as a JSON line (kept if the run fails)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def attach(self, live) -> None:
        self._thread = threading.Thread(target=self._run, args=(live,), name="soak sampler", daemon=True)
        self._thread.start()

    def _run(self, live) -> None:
        t0 = time.monotonic()
        done = 0
        while not self._stop.wait(self.period_s):
            status = live.status()
            lat = np.asarray(status["latency_ns"][done:], float) * 1e-6
            done += len(lat)
            pid = status["mapper_pid"]
            self.samples.append({
                "t_s": round(time.monotonic() - t0, 1),
                "rss_main_mb": rss_mb(), "rss_mapper_mb": rss_mb(pid) if pid else None,
                "frames_in": status["frames_in"], "frames_mapped": status["frames_processed"],
                "keyframes": status["keyframes"], "map_points": status["map_points"],
                "latency_p50_ms": float(np.percentile(lat, 50)) if len(lat) else None,
                "latency_p99_ms": float(np.percentile(lat, 99)) if len(lat) else None,
                "degraded": status["degraded"], "phase": "final map" if status["finishing"] else "live",
            })
            if self.stream:
                with open(self.stream, "a", encoding="utf-8") as fh:
                    fh.write(json.dumps(self.samples[-1]) + "\n")

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)


def _growth_mb_per_min(samples: list[dict], key: str, after_s: float) -> float | None:
    pts = [(s["t_s"], s[key]) for s in samples if s["t_s"] >= after_s and s[key] is not None and s["phase"] == "live"]
    if len(pts) < 3:
        return None
    t, v = np.array(pts).T
    return float(np.polyfit(t / 60.0, v, 1)[0])


def summarize(samples: list[dict], warmup_s: float, stretch_s: float) -> dict:
    """Memory and latency while live; the final global BA after capture stops is reported apart."""
    out = {}
    live = [s for s in samples if s["phase"] == "live"]
    for key in ("rss_main_mb", "rss_mapper_mb"):
        vals = [s[key] for s in live if s[key] is not None]
        final = [s[key] for s in samples if s["phase"] != "live" and s[key] is not None]
        out[key] = {"first": vals[0] if vals else None, "max": max(vals) if vals else None,
                    "last": vals[-1] if vals else None, "max_during_final_map": max(final) if final else None,
                    "growth_mb_per_min_after_warmup": _growth_mb_per_min(samples, key, warmup_s)}
    samples = live
    end = samples[-1]["t_s"] if samples else 0.0
    for name, lo, hi in (("first", warmup_s, warmup_s + stretch_s), ("last", end - stretch_s, end + 1)):
        sel = [s for s in samples if lo <= s["t_s"] < hi and s["latency_p99_ms"] is not None]
        out[f"latency_{name}_stretch"] = {
            "from_s": lo, "median_p50_ms": float(np.median([s["latency_p50_ms"] for s in sel])) if sel else None,
            "median_p99_ms": float(np.median([s["latency_p99_ms"] for s in sel])) if sel else None}
    return out


def format_table(r: dict) -> str:
    s, f = r["summary"], r["frames"]
    mm = s["rss_main_mb"], s["rss_mapper_mb"]
    a, b = s["latency_first_stretch"], s["latency_last_stretch"]

    def num(v, fmt="{:.0f}"):
        return "n/a" if v is None else fmt.format(v)

    return "\n".join([
        f"soak: {r['minutes']:g} min of the live pipeline on the simulated {r['scene']}, {r['resolution']} at "
        f"{r['fps_target']:g} fps ({r['device']}, {r['tracker']} tracker, {r['cpus']} CPUs)",
        f"frames in {f['in']}, mapped {f['processed']}, dropped {f['dropped']}; keyframes {r['keyframes']}, "
        f"landmarks {r['landmarks']}, final BA {num(r['final_ba_s'], '{:.1f}')} s",
        "| process | RSS first MB | max MB (live) | last MB (live) | growth after warm-up MB/min | max MB (final map) |",
        "|---|---|---|---|---|---|",
        *(f"| {name} | {num(m['first'])} | {num(m['max'])} | {num(m['last'])} | "
          f"{num(m['growth_mb_per_min_after_warmup'], '{:.2f}')} | {num(m['max_during_final_map'])} |"
          for name, m in (("main", mm[0]), ("mapper", mm[1]))),
        f"latency p50/p99 ms (medians of {r['summary']['latency_first_stretch']['from_s']:.0f} s-on samples): "
        f"first stretch {num(a['median_p50_ms'])}/{num(a['median_p99_ms'])}, last stretch "
        f"{num(b['median_p50_ms'])}/{num(b['median_p99_ms'])}",
    ])
