"""The tracking funnel: how many features each stage kept, so a run with few points says which stage lost them.

The front-end's stages are counted per frame and summed over the run (``corners``: features started;
``after_lk``: tracks Lucas-Kanade followed into a frame; ``after_drift_check``: those the drift check kept); the
mapper's are distinct tracks (``candidates``: tried for a point; ``triangulated``: got one; ``inliers``: kept by
the final robust bundle adjustment).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lapreco_hil.types import FUNNEL_STAGES

# a stage that keeps less than this share of what reached it is named as the one that lost the points
LOSSY_SHARE = 0.5


@dataclass
class Funnel:
    counts: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FUNNEL_STAGES, 0))

    def add(self, counts: dict[str, int]) -> None:
        for stage, n in counts.items():
            if stage in self.counts:
                self.counts[stage] += int(n)

    def as_dict(self) -> dict[str, int]:
        return dict(self.counts)

    def losses(self) -> list[tuple[str, str, float]]:
        """(stage, the stage before it, share kept) for each step between counts of the same thing: the per-frame
        sums, then the distinct tracks. Without any LK step (a single frame of a stereo rig: its candidates are
        left-right matches of the corners) the corners lead to the candidates directly."""
        c = self.counts
        steps = [("after_drift_check", "after_lk"), ("triangulated", "candidates"), ("inliers", "triangulated")]
        if c["after_lk"] == 0:
            steps.insert(1, ("candidates", "corners"))
        return [(b, a, c[b] / c[a]) for b, a in steps if c[a] > 0]

    def lossy_stage(self) -> str | None:
        """The first step that kept less than ``LOSSY_SHARE`` of what reached it (what it lost starved every
        step after it), or "corners" when none were found; None when no step was lossy."""
        if self.counts["corners"] == 0:
            return "corners"
        return next((stage for stage, _, kept in self.losses() if kept < LOSSY_SHARE), None)

    def summary(self) -> str:
        """One line, each group of counts of the same thing together, with the lossy step named:
        ``corners 351 started | per frame, summed: after_lk 259 -> after_drift_check 9 | distinct tracks: ...``."""
        c = self.counts
        line = (f"corners {c['corners']} started | per frame, summed: after_lk {c['after_lk']} -> after_drift_check "
                f"{c['after_drift_check']} | distinct tracks: candidates {c['candidates']} -> triangulated "
                f"{c['triangulated']} -> inliers {c['inliers']}")
        lossy = self.lossy_stage()
        return line + (f" (most were lost at {lossy})" if lossy else "")
