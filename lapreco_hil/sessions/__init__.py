"""Sessions: what was captured (frames, joint readings or camera poses, camera and robot description,
optional ground truth; one camera or a rig of cameras) in the documented, versioned folder format of
docs/session-format.md."""

from lapreco_hil.sessions.format import FORMAT, VERSION, VERSIONS, PoseSigma, SessionMeta
from lapreco_hil.sessions.session import Session
from lapreco_hil.sessions.writer import SessionWriter

__all__ = ["FORMAT", "VERSION", "VERSIONS", "PoseSigma", "Session", "SessionMeta", "SessionWriter"]
