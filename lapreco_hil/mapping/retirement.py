"""Bounded memory for a run as long as an operation: past ``active_keyframes`` the oldest keyframes are
retired. Their frames get their final poses (the robot prior with the keyframe corrections interpolated in
time), their landmarks are labelled and archived, and their observations are let go. This object keeps the
bookkeeping that needs: where the active keyframes start, which frames are final, which keyframes were
emptied, the tracks retired with them, and for each keyframe the tracks last seen in it (a retirement finds its
tracks without scanning them all)."""

from __future__ import annotations

import numpy as np

from lapreco_hil.config import MapperConfig
from lapreco_hil.geometry import interpolate_poses, inv_T
from lapreco_hil.mapping.keyframes import FrameRecord, Keyframe


class Retirement:
    def __init__(self, config: MapperConfig) -> None:
        self.active_keyframes = config.active_keyframes  # 0: never retire
        self.batch = max(1, min(config.retire_batch, config.active_keyframes // 2))
        self.window_keyframes = config.window_keyframes
        self.first_active = 0  # keyframes before this one are retired
        self.frames_final = 0  # frames before this index have their final pose
        self.emptied = 0  # keyframes before this index hold no observations any more
        self._last_seen_in: dict[int, set[int]] = {}  # keyframe id -> the tracks last seen in it
        self._retired_tracks: set[int] = set()

    def is_retired(self, track: int) -> bool:
        """A track that outlived the keyframes it was archived with: its landmark is final."""
        return track in self._retired_tracks

    def seen(self, track: int, kf_id: int, before: int | None) -> None:
        """The track was seen in keyframe ``kf_id``, last seen before in keyframe ``before`` (None: new)."""
        if before is not None:
            self._last_seen_in[before].discard(track)
        self._last_seen_in.setdefault(kf_id, set()).add(track)

    @property
    def retired_tracks(self) -> set[int]:
        """The tracks ``is_retired`` says are (the set itself, for a loop over a keyframe's tracks: read only)."""
        return self._retired_tracks

    def seen_in(self, kf_id: int, tracks: list[int], before: list[int | None]) -> None:
        """``seen`` for many tracks of keyframe ``kf_id`` at once; ``before[i]``: where ``tracks[i]`` was last seen."""
        last_seen_in = self._last_seen_in
        for track, k in zip(tracks, before):
            if k is not None:
                last_seen_in[k].discard(track)
        last_seen_in.setdefault(kf_id, set()).update(tracks)

    def _over(self, n_keyframes: int) -> int:
        return n_keyframes - self.first_active - self.active_keyframes

    def batch_due(self, n_keyframes: int, deferred: bool) -> int | None:
        """The cutoff of a batch retirement when the map is over its bound (by more than a batch when
        retirement is otherwise left to idle moments), else None."""
        if self.active_keyframes and self._over(n_keyframes) > (self.batch if deferred else 0):
            return self.first_active + self.batch
        return None

    def one_due(self, n_keyframes: int) -> int | None:
        """The cutoff that retires the oldest active keyframe when the map is over its bound, else None."""
        if self.active_keyframes and self._over(n_keyframes) > 0:
            return self.first_active + 1
        return None

    def take_tracks(self, cutoff: int) -> list[int]:
        """The tracks last seen before keyframe ``cutoff``, oldest keyframe first; they are retired now."""
        retired = [t for k in sorted(k for k in self._last_seen_in if k < cutoff)
                   for t in sorted(self._last_seen_in.pop(k))]
        self._retired_tracks.update(retired)
        return retired

    def take_frames(self, frames: list[FrameRecord], t_cut: int | None = None) -> list[FrameRecord]:
        """The frames not yet final that lie before ``t_cut`` (None: all); they are final once the caller
        settles them."""
        n = self.frames_final
        while n < len(frames) and (t_cut is None or frames[n].t_ns < t_cut):
            n += 1
        taken, self.frames_final = frames[self.frames_final:n], n
        return taken

    def take_keyframes_to_empty(self, keyframes: list[Keyframe], cutoff: int) -> list[Keyframe]:
        """The retired keyframes whose observations can go: no local window reaches back to them any more
        (a keyframe retired at ``cutoff`` still anchors, fixed, the windows just after it)."""
        reach = max(0, cutoff - 3 * self.window_keyframes)
        taken = keyframes[self.emptied:reach]
        self.emptied = max(self.emptied, reach)
        return taken

    def advance(self, cutoff: int) -> None:
        """Keyframes before ``cutoff`` are retired now."""
        self.first_active = cutoff

    def corrections(self, keyframes: list[Keyframe], upto: int | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
        """Times and corrections of the robot prior (T_refined @ T_prior^-1) of the keyframes an unsettled
        frame can lie between (frames before the first active keyframe are settled already), up to keyframe
        ``upto`` (all by default)."""
        kfs = [k for k in keyframes[max(0, self.first_active - 1):None if upto is None else upto + 1]
               if k.reference is None]  # a stereo partner moves with its reference (same time, same correction)
        return np.array([k.t_ns for k in kfs]), [k.T_world_camera @ inv_T(k.prior.T_world_camera) for k in kfs]


def corrections_at(kt: np.ndarray, corr: list[np.ndarray], t_ns: np.ndarray) -> np.ndarray:
    """The keyframe corrections (``Retirement.corrections``) interpolated at each of the times ``t_ns`` (held at
    the ends): (N, 4, 4)."""
    t = np.asarray(t_ns, np.int64)
    C = np.asarray(corr, float).reshape(-1, 4, 4)
    i = np.searchsorted(kt, t)
    out = np.empty((len(t), 4, 4))
    out[i == 0], out[i >= len(kt)] = C[0], C[-1]
    mid = np.flatnonzero((i > 0) & (i < len(kt)))
    if len(mid):
        j = i[mid]
        s = (t[mid] - kt[j - 1]) / (kt[j] - kt[j - 1])
        out[mid] = interpolate_poses(C[j - 1], C[j], s)
    return out

