"""Sessions: what was captured (frames, joint readings or camera poses, camera and robot description,
optional ground truth) in the documented, versioned folder format of docs/session-format.md."""

from lapreco_hil.sessions.format import FORMAT, VERSION, PoseSigma, SessionMeta
from lapreco_hil.sessions.session import Session
from lapreco_hil.sessions.writer import SessionWriter

__all__ = ["FORMAT", "VERSION", "PoseSigma", "Session", "SessionMeta", "SessionWriter"]
