from lapreco_hil.drivers.tracker.base import TrackerDriver

__all__ = ["TrackerDriver"]
