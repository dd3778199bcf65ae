"""Warp kernels of the dense surface (private); host wrappers in lapreco_hil.dense take a device."""
