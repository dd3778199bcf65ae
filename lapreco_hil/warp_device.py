"""Choosing the Warp device: ``auto`` takes CUDA when there is one, else the CPU.

Warp prints a banner and, on machines without a GPU driver, a C-level warning on stderr at ``init``; the app
routes both to its log instead, so the command line shows only what the user needs.
"""

from __future__ import annotations

import logging
import os
import sys
import tempfile
import threading

from lapreco_hil.errors import DeviceError

log = logging.getLogger(__name__)


def init_warp():
    """Import and initialise Warp quietly (idempotent); returns the module."""
    import warp as wp

    if hasattr(wp.config, "log_level"):
        wp.config.log_level = getattr(wp, "LOG_WARNING", 30)
    wp.config.quiet = True
    # wp.init() is idempotent; only its first call prints
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode(errors="replace").strip()
    if text:
        log.info("warp: %s", text)
    return wp


def resolve_device(name: str = "auto") -> str:
    wp = init_warp()
    has_cuda = wp.is_cuda_available()
    if name == "auto":
        return "cuda:0" if has_cuda else "cpu"
    if name.startswith("cuda") and not has_cuda:
        raise DeviceError(f"--device {name}: no CUDA device is visible to Warp on this machine; use --device cpu")
    if name not in ("cpu",) and not name.startswith("cuda"):
        raise DeviceError(f"--device {name}: expected auto, cpu, cuda or cuda:N")
    return "cuda:0" if name == "cuda" else name


# Warp's "current stream" is one per device for the whole process, not per thread: a kernel launched by one
# thread while another captures a CUDA graph lands in the capture and breaks it. Threads that drive the same
# device (the live runtime's capture thread rendering the simulated camera, its tracking thread running the
# front-end) take turns through this lock; it guards that process-wide device state, nothing else.
_DEVICE_LOCKS: dict[str, threading.RLock] = {}
_DEVICE_LOCKS_GUARD = threading.Lock()


def device_lock(device) -> threading.RLock:
    key = str(device)
    with _DEVICE_LOCKS_GUARD:
        return _DEVICE_LOCKS.setdefault(key, threading.RLock())


def preload_kernels(package: str, device) -> float:
    """Compile and load every Warp module under ``package`` (e.g. ``lapreco_hil.frontend.warp``) on ``device``
    now, returning the seconds it took. Warp compiles a module at its first launch; a live stage that meets a
    kernel for the first time mid-run (the first frame with a motion, the first BA) would stall for the
    compile — seconds on a machine whose kernel cache is cold — while capture goes on and drops frames."""
    import importlib
    import pkgutil
    import sys
    import time

    wp = init_warp()
    t0 = time.perf_counter()
    root = importlib.import_module(package)
    # load_module(recursive=True) loads the submodules already imported: import them all first
    for info in pkgutil.walk_packages(getattr(root, "__path__", []), package + "."):
        importlib.import_module(info.name)
    wp.load_module(root, device=str(device), recursive=True)
    # kernels made by a factory (module="unique": LK's, the Schur sums') each have a module of their own, which
    # the package's load leaves out
    for name, mod in list(sys.modules.items()):
        if mod is not None and (name == package or name.startswith(package + ".")):
            for kernel in [v for v in vars(mod).values() if isinstance(v, wp.Kernel)]:
                if kernel.module.name != kernel.func.__module__:
                    wp.load_module(kernel.module, device=str(device))
    seconds = time.perf_counter() - t0
    log.info("warp: %s loaded on %s in %.2f s", package, device, seconds)
    return seconds
