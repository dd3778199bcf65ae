"""The tracking funnel: how many features each stage kept, so a run with few points says which stage lost them.

``frames`` counts the frames the mapper took. The front-end's stages are counted per frame and summed over the
run (``corners``: features started; ``after_lk``: tracks Lucas-Kanade followed into a frame; ``after_drift_check``:
those the drift check kept); a run of one frame has no tracking over time and says so. The mapper's are distinct
tracks (``candidates``: tried for a point; ``triangulated``: got one; ``inliers``: kept by the final robust
bundle adjustment). A stereo rig's run adds its left-right matching at keyframes, distinct tracks too
(``partner_searched``: searched for in a partner camera's image; ``partner_matched``: found there at least once;
``without_partner``: never found and never a candidate, so lost for want of a partner match).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lapreco_hil.types import FUNNEL_STAGES

# a stage that keeps less than this share of what reached it is named as the one that lost the points
LOSSY_SHARE = 0.5
RIG_STAGES = ("partner_searched", "partner_matched", "without_partner")
# what the summary calls a stage it names as lossy, where its key would not say it
STAGE_NAMES = {"partner_matched": "left-right matching"}


def _stages(rig: bool) -> dict[str, int]:
    return dict.fromkeys(("frames",) + FUNNEL_STAGES + (RIG_STAGES if rig else ()), 0)


@dataclass
class Funnel:
    counts: dict[str, int] = field(default_factory=lambda: _stages(rig=False))

    @staticmethod
    def for_rig() -> "Funnel":
        """A stereo rig's funnel: the left-right matching's counts too."""
        return Funnel(_stages(rig=True))

    @property
    def rig(self) -> bool:
        return "partner_searched" in self.counts

    @property
    def tracked_over_time(self) -> bool:
        """Whether tracks were followed from frame to frame (a report from before ``frames`` was counted: yes)."""
        return self.counts.get("frames", 2) != 1

    def add(self, counts: dict[str, int]) -> None:
        for stage, n in counts.items():
            if stage in self.counts:
                self.counts[stage] += int(n)

    def as_dict(self) -> dict[str, int]:
        return dict(self.counts)

    def losses(self) -> list[tuple[str, str, float]]:
        """(stage, the stage before it, share kept) for each step between counts of the same thing: the per-frame
        sums, a rig's left-right matching (kept: the searched tracks not lost for want of a partner), then the
        distinct tracks. Without any LK step and without a rig's counts (an older report of a stereo frame) the
        corners lead to the candidates directly."""
        c = self.counts
        kept = []
        if self.tracked_over_time and c["after_lk"] > 0:
            kept.append(("after_drift_check", "after_lk", c["after_drift_check"] / c["after_lk"]))
        if self.rig and c["partner_searched"] > 0:
            searched = c["partner_searched"]
            kept.append(("partner_matched", "partner_searched", (searched - c["without_partner"]) / searched))
        elif c["after_lk"] == 0 and c["corners"] > 0:
            kept.append(("candidates", "corners", c["candidates"] / c["corners"]))
        kept += [(b, a, c[b] / c[a]) for b, a in (("triangulated", "candidates"), ("inliers", "triangulated"))
                 if c[a] > 0]
        return kept

    def lossy_stage(self) -> str | None:
        """The first step that kept less than ``LOSSY_SHARE`` of what reached it (what it lost starved every
        step after it), or "corners" when none were found; None when no step was lossy."""
        if self.counts["corners"] == 0:
            return "corners"
        return next((stage for stage, _, kept in self.losses() if kept < LOSSY_SHARE), None)

    def summary(self) -> str:
        """One line, each group of counts of the same thing together, with the lossy step named:
        ``corners 351 started | per frame, summed: after_lk 259 -> after_drift_check 9 | distinct tracks: ...``;
        a rig's left-right matching is a group of its own, and a run of one frame says it tracked nothing over
        time in place of the per-frame sums."""
        c = self.counts
        groups = [f"corners {c['corners']} started"]
        if self.tracked_over_time:
            groups.append(f"per frame, summed: after_lk {c['after_lk']} -> after_drift_check {c['after_drift_check']}")
        else:
            groups.append("one frame: no tracking over time")
        if self.rig:
            groups.append(f"left-right matching: {c['partner_matched']} of {c['partner_searched']} tracks found in a "
                          f"partner view, {c['without_partner']} dropped for want of one (never a candidate)")
        groups.append(f"distinct tracks: candidates {c['candidates']} -> triangulated {c['triangulated']} -> "
                      f"inliers {c['inliers']}")
        lossy = self.lossy_stage()
        return " | ".join(groups) + (f" (most were lost at {STAGE_NAMES.get(lossy, lossy)})" if lossy else "")
