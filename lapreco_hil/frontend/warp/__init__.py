"""The Warp front-end: the seed's GPU tracker (undistort, pyramid, Shi-Tomasi, pyramidal KLT, Zinsser drift
check) as Warp kernels that run on CUDA when there is a GPU and on Warp's CPU device otherwise."""

from lapreco_hil.frontend.warp.frontend import WarpFrontEnd

__all__ = ["WarpFrontEnd"]
