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
        """(stage, the stage before it, share kept) for each step where both counts are known."""
        c = self.counts
        steps = [("after_drift_check", "after_lk"), ("triangulated", "candidates"), ("inliers", "triangulated")]
        return [(b, a, c[b] / c[a]) for b, a in steps if c[a] > 0]

    def lossy_stage(self) -> str | None:
        """The first step that kept less than ``LOSSY_SHARE`` of what reached it (what it lost starved every
        step after it), or "corners" when none were found; None when no step was lossy."""
        if self.counts["corners"] == 0:
            return "corners"
        return next((stage for stage, _, kept in self.losses() if kept < LOSSY_SHARE), None)

    def summary(self) -> str:
        """One line: ``corners 351 -> after_lk 259 -> ...``, with the lossy step named."""
        line = " -> ".join(f"{k} {v}" for k, v in self.counts.items())
        lossy = self.lossy_stage()
        return line + (f" (most were lost at {lossy})" if lossy else "")
