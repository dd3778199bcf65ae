"""``lapreco batch SESSIONS_DIR --out DIR``: every session of a folder replayed and evaluated as one Ray task
each, on a local Ray instance or an existing cluster; one failure never stops the rest, done sessions are
skipped (resumable), and the rows become a table and plots across sessions (lapreco_hil.batch).

Ray is imported only here, and only when a batch has work to do, so the other commands never load it."""

from __future__ import annotations

import logging
import os
import socket
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path

from lapreco_hil.app.replay import run_replay
from lapreco_hil.batch.rows import (DONE_FILE, SessionRow, failed_row, find_sessions, is_done, row_from_outputs)
from lapreco_hil.batch.summary import write_summary
from lapreco_hil.config import load_config
from lapreco_hil.errors import ConfigError, LaprecoError
from lapreco_hil.outputs import check_output_dir, prepare_output_dir, write_json

log = logging.getLogger(__name__)

# One thread of BLAS/OpenMP per task: a task is given one CPU, and N tasks on N cores must not each start N
# threads and fight over them.
TASK_ENV = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                   "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")}
# Ray takes a non-loopback node address unless told this is not a cluster host; a local instance is then
# loopback-only (every Ray server listens on 127.0.0.1). Read by Ray when it is imported.
RAY_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
LOCAL_OBJECT_STORE_BYTES = 128 * 1024 ** 2  # a task returns one small row; Ray's default takes 30% of the RAM


@dataclass(frozen=True)
class BatchOptions:
    """How each session is replayed (the options of ``lapreco replay``)."""

    tracker: str = "auto"
    device: str = "auto"  # auto: cuda when the task was given a GPU (--gpus-per-task), else cpu
    config_path: str | None = None


@dataclass(frozen=True)
class BatchResult:
    rows: tuple[SessionRow, ...]
    paths: dict = field(default_factory=dict)  # summary files by kind: csv, markdown, quality_plot, latency_plot
    wall_s: float = 0.0
    ran: int = 0  # sessions replayed by this run (the rest were done before)
    cluster: str = ""  # where the tasks ran, e.g. "a local Ray instance (2 CPUs)"
    skipped_folders: tuple[str, ...] = ()  # sub-folders with no session.json

    @property
    def failed(self) -> list[SessionRow]:
        return [r for r in self.rows if r.status != "ok"]

    def summary_line(self) -> str:
        earlier = sum(r.earlier for r in self.rows)
        line = (f"{len(self.rows)} session{'s' * (len(self.rows) != 1)}: {len(self.rows) - len(self.failed)} ok ({earlier} done before), "
                f"{len(self.failed)} failed")
        if self.failed:
            line += " (" + ", ".join(r.session for r in self.failed) + ")"
        if not self.ran:
            return line + "; nothing to replay"
        # the tasks' CPU time against the wall time: how many cores the batch really had
        cpu = sum(r.cpu_s or 0.0 for r in self.rows if not r.earlier)
        return line + f"; {self.ran} replayed in {self.wall_s:.1f} s (tasks' CPU time {cpu:.1f} s) on {self.cluster}"


def process_session(session: str, out_dir: str, options: BatchOptions) -> SessionRow:
    """Replay one session into ``out_dir`` and evaluate its points against the session's true surface (when it
    has one); the done file is written last. Never raises: a failure is a failed row with its one-line error."""
    name = Path(session).name
    host = socket.gethostname()
    t0, cpu0 = time.perf_counter(), time.process_time()
    out = Path(out_dir)
    try:
        (out / DONE_FILE).unlink(missing_ok=True)  # a redo that dies half-way must not look done
        report = run_replay(session, out_dir, tracker=options.tracker, device=options.device,
                            config_path=options.config_path, progress=False)
        evaluation, evaluation_error = _evaluate(session, out, report)
        write_json(out / DONE_FILE, {"status": "ok", "session": session, "host": host,
                                     "wall_s": time.perf_counter() - t0,
                                     # the task's CPU time: wall_s beyond it is time spent waiting for a core
                                     "cpu_s": time.process_time() - cpu0, "evaluation": evaluation,
                                     "evaluation_error": evaluation_error})
        return row_from_outputs(name, out)
    except LaprecoError as exc:
        return failed_row(name, str(exc), time.perf_counter() - t0, host, time.process_time() - cpu0)
    except Exception as exc:  # a bug or a library's failure on this session: the batch goes on
        log.debug("session %s failed", name, exc_info=True)
        return failed_row(name, f"{type(exc).__name__}: {exc}", time.perf_counter() - t0, host,
                          time.process_time() - cpu0)


def _evaluate(session: str, out: Path, report: dict) -> tuple[dict | None, str | None]:
    """Similarity ICP and coverage of the run's points against the session's true surface (lapreco evaluate's
    figures); (None, None) without one, (None, why) when the points cannot be evaluated."""
    from lapreco_hil.evaluation.compare import read_points_ply, read_report_camera, read_tum
    from lapreco_hil.evaluation.coverage import camera_view
    from lapreco_hil.evaluation.icp import evaluate_points
    from lapreco_hil.sessions import Session

    truth = Session(session).ground_truth()
    if truth is None or truth.surface is None:
        return None, None
    _, poses = read_tum(out / "trajectory.tum")
    K, size, mask = camera_view(read_report_camera(report["camera"]))  # what the real camera saw
    result = evaluate_points(read_points_ply(out / "points.ply"), truth.surface, poses, K, size, mask=mask)
    if "error" in result:
        return None, f"evaluate: {result['error']}"
    return result, None


def _ray_task(session: str, out_dir: str, options: BatchOptions) -> SessionRow:
    """The body of one Ray task (in a worker process)."""
    import cv2
    import ray

    cv2.setNumThreads(1)  # see TASK_ENV
    if options.device == "auto":
        # Ray gives a task its GPUs through CUDA_VISIBLE_DEVICES, so the task's first GPU is cuda:0
        options = replace(options, device="cuda:0" if ray.get_gpu_ids() else "cpu")
    return process_session(session, out_dir, options)


def _check_reachable(address: str) -> None:
    """A one-line error now for an address nobody answers at, instead of Ray's retries."""
    if address == "auto":
        return  # Ray looks for a cluster started on this machine and says so at once when there is none
    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--address {address}: expected HOST:PORT (the head's GCS, e.g. 10.0.0.1:6379), "
                          f"ray://HOST:10001 (Ray client) or auto")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=5.0):
            pass
    except OSError as exc:
        raise ConfigError(f"--address {address}: cannot reach a Ray cluster there ({exc.strerror or exc}); start "
                          f"one with `ray start --head` on that machine, or leave --address out for a local Ray "
                          f"instance") from None


@contextmanager
def ray_connection(address: str | None, workers: int | None):
    """Ray, connected: to the cluster at ``address``, or a new local instance with ``workers`` CPUs (default:
    this machine's), shut down afterwards. A connection the caller opened already is used and left open."""
    if address is None:
        os.environ.setdefault(RAY_LOOPBACK_ENV, "0")
    else:
        if workers is not None:
            raise ConfigError("--workers sizes a local Ray instance; with --address the cluster's nodes decide how "
                              "many tasks run at once")
        _check_reachable(address)
    import ray

    if ray.is_initialized():
        yield ray
        return
    if address is None and ray._private.ray_constants.ENABLE_RAY_CLUSTER:
        log.warning("Ray was imported before %s was set: the local Ray instance listens on every interface, "
                    "not only on loopback", RAY_LOOPBACK_ENV)
    kwargs = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
                  runtime_env={"env_vars": dict(TASK_ENV)})
    if address is None:
        kwargs.update(num_cpus=workers, object_store_memory=LOCAL_OBJECT_STORE_BYTES)
    try:
        # "local": a new instance even where RAY_ADDRESS names a cluster (only --address picks one)
        ray.init(address=address or "local", **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if address is None:
            raise ConfigError(f"cannot start a local Ray instance ({first})") from None
        raise ConfigError(f"--address {address}: cannot connect to a Ray cluster there ({first}); start one with "
                          f"`ray start --head`, or leave --address out for a local Ray instance") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def _check_resources(ray, gpus_per_task: float, address: str | None) -> str:
    """That some node can run a task (one CPU, ``gpus_per_task`` GPUs); otherwise Ray would wait for ever.
    Returns where the tasks run, in words."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    cpus = sum(r.get("CPU", 0) for r in nodes)
    gpus = sum(r.get("GPU", 0) for r in nodes)
    where = f"the Ray cluster at {address}" if address else "a local Ray instance"
    if not any(r.get("CPU", 0) >= 1 and r.get("GPU", 0) >= gpus_per_task for r in nodes):
        most = max((r.get("GPU", 0) for r in nodes), default=0)
        need = f"1 CPU and {gpus_per_task:g} GPUs" if gpus_per_task else "1 CPU"
        raise ConfigError(f"no node of {where} has {need} for a task (largest GPU count on a node: {most:g}); "
                          f"lower --gpus-per-task or add nodes with GPUs")
    at = ""
    if address is None:  # a local instance says where it listens (127.0.0.1: loopback only)
        at = " at " + ", ".join(sorted({n.get("NodeManagerAddress", "?") for n in ray.nodes() if n.get("Alive")}))
    return f"{where} ({len(nodes)} node{'s' * (len(nodes) != 1)}{at}, {cpus:g} CPUs, {gpus:g} GPUs)"


def _ray_error_line(exc: Exception) -> str:
    """A Ray failure (worker crashed, node lost, task cancelled) in one line."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text[:300]}"


def run_batch(sessions_dir: str, out: str, *, address: str | None = None, workers: int | None = None,
              gpus_per_task: float = 0.0, options: BatchOptions = BatchOptions(), force: bool = False,
              progress: bool = True) -> BatchResult:
    """Replay and evaluate every session under ``sessions_dir`` into ``out``/<session>/ as Ray tasks, then write
    ``out``/summary.csv, summary.md and the plots. Sessions done by an earlier run are read back unless
    ``force``."""
    from tqdm import tqdm

    if gpus_per_task < 0:
        raise ConfigError(f"--gpus-per-task {gpus_per_task:g}: must be >= 0")
    sessions, others = find_sessions(sessions_dir)
    for folder in others:
        log.warning("%s: no session.json; not a session, skipped", folder)
    load_config(options.config_path)  # a bad configuration is one error here, not one per task
    if options.config_path:  # a task's working folder is not this one
        options = replace(options, config_path=str(Path(options.config_path).absolute()))
    check_output_dir(out)
    # absolute, not resolved: on a cluster the shared storage's path (a link, perhaps) is what every node sees
    out_dir = prepare_output_dir(out).absolute()
    rows: dict[str, SessionRow] = {}
    todo = []
    for session in sessions:
        target = out_dir / session.name
        if not force and is_done(target):
            try:
                rows[session.name] = row_from_outputs(session.name, target, earlier=True)
                continue
            except (OSError, ValueError, KeyError):  # unreadable outputs: replay it again
                log.warning("%s: earlier outputs unreadable; replaying it again", target)
        todo.append(session)
    log.info("batch: %d sessions, %d to replay", len(sessions), len(todo))
    t0 = time.perf_counter()
    cluster = ""
    if todo:
        with ray_connection(address, workers) as ray:
            cluster = _check_resources(ray, gpus_per_task, address)
            log.info("batch: %d tasks on %s", len(todo), cluster)
            task = ray.remote(_ray_task).options(num_cpus=1, num_gpus=gpus_per_task, max_retries=1)
            names = {task.remote(str(s.absolute()), str(out_dir / s.name), options): s.name for s in todo}
            pending = list(names)
            bar = tqdm(total=len(pending), desc="batch", unit="session", file=sys.stderr, disable=not progress)
            try:
                with bar:
                    while pending:
                        ready, pending = ray.wait(pending, num_returns=1)
                        for ref in ready:
                            name = names[ref]
                            try:
                                row = ray.get(ref)
                            except ray.exceptions.RayError as exc:
                                row = failed_row(name, _ray_error_line(exc))
                            rows[name] = row
                            log.info("batch: %s %s%s", name, row.status, f": {row.error}" if row.error else "")
                            bar.update(1)
            except KeyboardInterrupt:
                for ref in pending:
                    ray.cancel(ref, force=True)
                raise
    wall_s = time.perf_counter() - t0
    ordered = tuple(rows[s.name] for s in sessions)
    paths = write_summary(list(ordered), out_dir, title=f"lapreco batch: {Path(sessions_dir).name}")
    return BatchResult(rows=ordered, paths=paths, wall_s=wall_s, ran=len(todo), cluster=cluster,
                       skipped_folders=tuple(str(p) for p in others))
