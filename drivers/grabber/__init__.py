from .base import Grabber

__all__ = ["Grabber"]
