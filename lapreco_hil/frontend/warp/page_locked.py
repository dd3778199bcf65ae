"""Frames in page-locked (pinned) host memory, so the Warp front-end uploads a frame by one DMA and converts it
to grey on the device, instead of converting it on the host in the tracking thread.

The capture thread copies each frame into a free buffer of a :class:`PageLockedFrames` pool (``stage``): that
copy runs beside the tracking of the previous frame, off the frame's critical path. The front-end recognises
such a frame by its memory (``page_locked_source``) and takes the short path; any other frame takes the host
path, with the same grey levels (the device conversion is OpenCV's fixed-point BGR2GRAY, bit for bit).

A buffer is free once nothing refers to the frame image it was handed out as: every view of it (the frame,
its slices, a recorder's queue) holds a reference to the buffer's numpy array, which the pool counts. With every
buffer held, a frame is passed on as it came (counted), never overwritten under its reader."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import warp as wp

from lapreco_hil.types import Frame

# nothing differentiates these kernels, so no adjoints: they only add compile time
wp.set_module_options({"enable_backward": False})


@wp.kernel
def _bgr_to_grey(bgr: wp.array3d(dtype=wp.uint8), grey: wp.array2d(dtype=wp.uint8)):
    """OpenCV's COLOR_BGR2GRAY for 8-bit images: weights 0.114, 0.587, 0.299 in 15-bit fixed point, rounded."""
    y, x = wp.tid()
    b = int(bgr[y, x, 0])
    g = int(bgr[y, x, 1])
    r = int(bgr[y, x, 2])
    grey[y, x] = wp.uint8((b * 3735 + g * 19235 + r * 9798 + 16384) >> 15)


def bgr_to_grey(bgr: wp.array, grey: wp.array, device) -> None:
    """``grey`` (H x W uint8) <- the grey levels of ``bgr`` (H x W x 3 uint8, on ``device``)."""
    wp.launch(_bgr_to_grey, dim=grey.shape, inputs=[bgr, grey], device=device)


def page_locked_source(image: np.ndarray):
    """The Warp host array that ``image`` is the whole of (a frame handed out by :class:`PageLockedFrames`),
    else None."""
    root = image.base
    if not isinstance(root, np.ndarray) or not isinstance(root.base, wp.array):
        return None
    owner = root.base
    if owner.device.is_cuda or image.shape != root.shape or image.dtype != root.dtype:
        return None
    if image.ctypes.data != root.ctypes.data or not image.flags.c_contiguous:
        return None
    return owner


class PageLockedFrames:
    """A pool of ``count`` page-locked buffers for frames of ``shape`` (H, W, 3) uint8 (plain host memory when
    ``device`` is not a CUDA device, so the path runs on the CPU device too)."""

    def __init__(self, shape: tuple[int, int, int], count: int, device) -> None:
        if count < 1:
            raise ValueError(f"a page-locked frame pool needs at least one buffer, not {count}")
        self.shape = tuple(shape)
        pinned = wp.get_device(device).is_cuda
        self._buffers = [wp.empty(self.shape, dtype=wp.uint8, device="cpu", pinned=pinned) for _ in range(count)]
        self._roots = [b.numpy() for b in self._buffers]
        root = self._roots[0]
        self._free_refs = sys.getrefcount(root)  # a root nothing else refers to (counted as ``stage`` counts)
        del root
        self._next = 0
        self.staged = 0  # frames copied into a buffer
        self.passed_on = 0  # frames passed on as they came: another shape, or every buffer still held

    def stage(self, frame: Frame) -> Frame:
        """``frame`` with its image copied into a free buffer; as it came where none is free or it does not fit."""
        image = frame.image
        if image.shape != self.shape or image.dtype != np.uint8:
            self.passed_on += 1
            return frame
        n = len(self._roots)
        for k in range(n):
            i = (self._next + k) % n
            root = self._roots[i]
            if sys.getrefcount(root) <= self._free_refs:
                np.copyto(root, image)
                self._next = (i + 1) % n
                self.staged += 1
                return dataclasses.replace(frame, image=root[...])
        self.passed_on += 1
        return frame
