"""Kernels are compiled before a live run needs them, and capture drops say when they happened."""

import sys
import time

import pytest

from lapreco_hil.runtime.metrics import LiveMetrics


def _warp_modules(package: str):
    wp = pytest.importorskip("warp")
    return [wp.get_module(name) for name, mod in sys.modules.items()
            if name.startswith(package + ".") and mod is not None
            and any(getattr(v, "module", None) is not None and type(v).__name__ == "Kernel" for v in vars(mod).values())]


def test_preload_loads_every_frontend_kernel_module_on_the_device():
    """The motion path's kernels (predict) are launched only for frames with a motion; preloading must load them
    with the rest, or a live run compiles them mid-run under the device lock."""
    from lapreco_hil.warp_device import preload_kernels, resolve_device

    device = resolve_device("cpu")
    preload_kernels("lapreco_hil.frontend.warp", device)
    modules = _warp_modules("lapreco_hil.frontend.warp")
    names = {m.name for m in modules}
    assert "lapreco_hil.frontend.warp.predict" in names and len(names) >= 5, names
    unloaded = [m.name for m in modules if not m.execs]
    assert not unloaded, f"not loaded on {device}: {unloaded}"


def test_preload_loads_the_kernels_a_factory_made_too():
    """LK's kernel and the Schur solver's camera-system sums are made by factories, each in a module of its own
    (module="unique") that loading the package leaves out: the BA worker's first final-style elimination, or a
    front-end without a warm-up, would compile them mid-run."""
    from lapreco_hil.frontend.warp import lk
    from lapreco_hil.mapping import schur_kernels
    from lapreco_hil.warp_device import preload_kernels, resolve_device

    device = resolve_device("cpu")
    preload_kernels("lapreco_hil.mapping.schur_kernels", device)
    preload_kernels("lapreco_hil.frontend.warp", device)
    for kernel in (schur_kernels._schur_blocks, schur_kernels._schur_blocks_band, lk._lk_track_slots,
                   lk._lk_track_resampled):
        assert kernel.module.name != kernel.func.__module__  # (a module of its own)
        assert kernel.module.execs, f"{kernel.key} not loaded on {device}"


def test_marked_drops_report_when_they_happened():
    m = LiveMetrics()
    m.mark("dropped_capture")
    time.sleep(0.02)
    m.mark("dropped_capture")
    assert m.get("dropped_capture") == 2
    first, last = m.event_span_ns["dropped_capture"]
    assert last - first >= 15_000_000
