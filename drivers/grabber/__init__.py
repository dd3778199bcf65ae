from lapreco_hil.drivers.grabber.base import Grabber

__all__ = ["Grabber"]
