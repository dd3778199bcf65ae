"""Starts and stops the live run's threads and processes, and owns the shutdown order.

A stage that raises is stored and reported (``errors``); an essential one (capture, tracking, the mapper)
stops the run, an optional one (surface, dense, record, health) is switched off under ``on_stage_error = "degrade"``
and the run goes on. A mapper or BA worker process that dies is always fatal. Nothing dies silently.

Shutdown, in order: capture stops; tracking finishes what capture kept; the mapper is asked for its final
map (while the BA worker and the mapper are watched, so one killed meanwhile is reported at once); both
processes end; the results reader ends after the mapper's last message; then surface, dense, record and health;
last the shared memory is unlinked."""

from __future__ import annotations

import logging
import threading
import time

from lapreco_hil.runtime.metrics import LiveMetrics
from lapreco_hil.runtime.processes import MapperProcesses
from lapreco_hil.runtime.stages import StageLinks

log = logging.getLogger(__name__)
ESSENTIAL = ("capture", "tracking", "mapper")
MAPPER_START_TIMEOUT_S = 120.0  # for the mapper process to be up before capture starts
WATCH_PERIOD_S = 0.05


class Supervisor:
    def __init__(self, processes: MapperProcesses, links: StageLinks, metrics: LiveMetrics, *,
                 on_stage_error: str) -> None:
        self.processes, self.links, self.metrics = processes, links, metrics
        self.on_stage_error = on_stage_error
        self.errors: dict[str, str] = {}  # stage -> "Type: message"
        self.threads: dict[str, threading.Thread] = {}
        self.interrupted = False  # Ctrl-C (or SIGTERM) ended the run
        self.final = None  # the mapper's FinalMap or MapperFailed
        self.wall_s = 0.0

    def _guard(self, name: str, body) -> None:
        try:
            body()
        except BaseException as exc:  # stored, reported by the main loop
            log.error("live stage '%s' failed: %s", name, exc, exc_info=True)
            self.errors[name] = f"{type(exc).__name__}: {exc}"
            if name in ESSENTIAL or self.on_stage_error == "stop":
                self.links.stop.set()
            else:
                self.links.disabled.add(name)
                self.metrics.add(f"{name}_disabled")
        finally:
            if name == "capture":
                self.links.capture_done.set()
                self.links.notify()

    def start_processes(self) -> None:
        """The mapper (and BA worker) up before capture starts: frames taken while it started would wait in the
        ring for a second or two and set the latency tail of the whole run."""
        try:
            self.processes.start()
        except BaseException:  # (shared memory full, a process that cannot start): nothing left behind
            self.processes.stop()
            self.processes.close()
            raise
        try:
            self.processes.wait_ready(MAPPER_START_TIMEOUT_S)
        except KeyboardInterrupt:  # Ctrl-C while the mapper starts: end as from the main loop, cleanly
            self.interrupted = True
            self.links.stop.set()

    def run(self, stages: dict, seconds: float | None) -> None:
        """Run the stage bodies (name -> callable) in threads until the source ends, ``seconds`` pass, a fatal
        error or Ctrl-C; then shut down in order. The outcome is in ``final``, ``errors`` and ``wall_s``."""
        self.threads = {name: threading.Thread(target=self._guard, args=(name, body), name=f"live {name}",
                                               daemon=True) for name, body in stages.items()}
        t_start = time.perf_counter()
        for th in self.threads.values():
            th.start()
        try:
            self._watch(t_start, seconds)
        except KeyboardInterrupt:
            self.interrupted = True  # Ctrl-C: stop capturing, map what was tracked, write everything
            log.warning("interrupted: finishing the map and writing the outputs")
        finally:
            self._shutdown()
            self.wall_s = time.perf_counter() - t_start

    def _watch(self, t_start: float, seconds: float | None) -> None:
        procs = self.processes
        while True:
            time.sleep(WATCH_PERIOD_S)
            with self.links.cond:
                self.metrics.sample_depth("mapper", procs.slots_in_use)
            if self.links.stop.is_set():
                return
            dead = procs.dead()
            if dead is not None:
                self.errors["mapper"] = dead
                if procs.mapper is not None and not procs.mapper.is_alive():
                    self.final = procs.last_word(1.0)  # its last word: the error that ended it
                return
            if seconds is not None and time.perf_counter() - t_start >= seconds:
                return
            if not self.threads["tracking"].is_alive():
                return  # the source ended and every kept frame was tracked

    def _shutdown(self) -> None:
        links, procs = self.links, self.processes
        links.stop.set()
        self.threads["capture"].join(timeout=5.0)
        self.threads["tracking"].join(timeout=30.0)
        if procs.mapper.is_alive():
            self.final, error = procs.finish()
            if error is not None:
                self.errors["mapper"] = error
        procs.stop()
        procs.end_results()
        self.threads["results"].join(timeout=10.0)
        links.finished.set()
        links.notify()
        for name in ("surface", "dense", "record", "health", "rig check"):
            if name in self.threads:
                self.threads[name].join(timeout=60.0)
        procs.close()

    def fatal_errors(self) -> dict[str, str]:
        return {k: v for k, v in self.errors.items() if k in ESSENTIAL or self.on_stage_error == "stop"}
