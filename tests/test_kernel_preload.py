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


def test_marked_drops_report_when_they_happened():
    m = LiveMetrics()
    m.mark("dropped_capture")
    time.sleep(0.02)
    m.mark("dropped_capture")
    assert m.get("dropped_capture") == 2
    first, last = m.event_span_ns["dropped_capture"]
    assert last - first >= 15_000_000
