"""lapreco-hil: live 3D reconstruction for robotic laparoscopy, hardware in the loop.

The core (this package) knows devices only through the small interfaces in ``lapreco_hil.drivers``;
simulators and real drivers are reached through :mod:`lapreco_hil.registry` by URL.
"""

__version__ = "0.1.0"
