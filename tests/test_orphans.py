"""A live run killed outright (kill -9: no handler, no cleanup in the main process) leaves nothing behind: its
mapper and local-BA worker end with it, and its shared memory is unlinked (by multiprocessing's resource
tracker once every process of the run is gone, or by the next run's start when even that was killed)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from multiprocessing import resource_tracker, shared_memory
from pathlib import Path

import pytest

from lapreco_hil.runtime.shm import new_segment_name, owner_pid, unlink_leftovers

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="walks /proc and /dev/shm")


def _start_time(pid: int) -> str | None:
    """The process's start time (field 22 of /proc/pid/stat), None once it is gone or a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()
    return None if fields[0] in ("Z", "X") else fields[19]


def _children(pid: int) -> set[int]:
    out = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            continue
    return out


def _descendants(pid: int) -> set[int]:
    found, todo = set(), [pid]
    while todo:
        for child in _children(todo.pop()) - found:
            found.add(child)
            todo.append(child)
    return found


def _shm_mapped(pid: int) -> set[str]:
    """The /dev/shm entries the process has mapped (its shared memory and multiprocessing's semaphores)."""
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return set()
    return {tok for line in maps.splitlines() for tok in line.split() if tok.startswith("/dev/shm/")}


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def test_kill_9_of_lapreco_run_leaves_no_process_and_no_shared_memory(tmp_path):
    config = tmp_path / "config.toml"
    config.write_text('[runtime]\nba_worker = "on"\n')  # the BA worker too, not only the mapper
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "lapreco_hil.cli.main", "run", "--robot", "sim://skull?width=256&height=192",
             "--grabber", "sim://skull?width=256&height=192", "--out", str(tmp_path / "out"), "--config", str(config),
             "--device", "cpu", "--tracker", "opencv", "--no-progress"],
            stdout=subprocess.DEVNULL, stderr=err)
    try:
        processes: dict[int, str] = {}  # pid -> start time, for every process of the run seen
        shm: set[str] = set()
        deadline = time.monotonic() + 180
        mapper = None
        while time.monotonic() < deadline and proc.poll() is None:
            for pid in _descendants(proc.pid):
                started = _start_time(pid)
                if started is not None:
                    processes.setdefault(pid, started)
                    shm |= _shm_mapped(pid)
                    # the mapper is up once it has attached the run's shared memory
                    if "spawn" in _cmdline(pid) and any("/lapreco_" in s for s in _shm_mapped(pid)):
                        mapper = pid
            if mapper is not None:
                break
            time.sleep(0.2)
        assert mapper is not None, "no mapper process appeared; stderr: " + (tmp_path / "stderr.txt").read_text()[-3000:]
        time.sleep(2.0)  # mapping now
        for pid in _descendants(proc.pid):
            processes.setdefault(pid, _start_time(pid))
            shm |= _shm_mapped(pid)
        shm |= _shm_mapped(proc.pid)
        spawned = [pid for pid in processes if "spawn_main" in _cmdline(pid)]
        assert len(spawned) >= 2, {pid: _cmdline(pid) for pid in processes}  # the mapper and the BA worker
        assert sum("/lapreco_" in s for s in shm) == 2, shm  # the observation ring and the map snapshot
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
    killed = time.monotonic()
    deadline = killed + 10.0
    while time.monotonic() < deadline:
        alive = {pid: _cmdline(pid) for pid, started in processes.items()
                 if started is not None and _start_time(pid) == started}
        left = {s for s in shm if os.path.exists(s)}
        if not alive and not left:
            break
        time.sleep(0.1)
    print(f"{len(processes)} processes and {len(shm)} /dev/shm entries of the run; all gone "
          f"{time.monotonic() - killed:.2f} s after kill -9")
    assert not alive, f"processes of the killed run still alive: {alive}"
    assert not left, f"shared memory of the killed run left: {left}"


def test_a_start_unlinks_the_shared_memory_of_killed_runs_only():
    gone = subprocess.Popen(["true"])
    gone.wait()  # a pid whose process has ended
    dead_name = f"lapreco_{gone.pid}_0badc0de"
    assert owner_pid(dead_name) == gone.pid and owner_pid("psm_1234") is None
    ours = shared_memory.SharedMemory(name=new_segment_name(), create=True, size=64)
    dead = shared_memory.SharedMemory(name=dead_name, create=True, size=64)
    try:
        removed = unlink_leftovers()
        assert dead_name in removed and ours.name not in removed
        assert not Path("/dev/shm", dead_name).exists() and Path("/dev/shm", ours.name).exists()
    finally:
        dead.close()
        resource_tracker.unregister(dead._name, "shared_memory")  # unlinked above, not by its owner
        ours.close()
        ours.unlink()
