"""``lapreco batch``: a folder of simulated sessions (and one broken one) replayed and evaluated as Ray tasks on
a local instance of 2 workers: the table and plots, one failure that does not stop the rest, resuming, --force;
and the one-line errors for a missing or empty sessions folder and an unreachable cluster."""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys

import pytest

from lapreco_hil.app.batch import BatchOptions, process_session, run_batch
from lapreco_hil.batch.rows import DONE_FILE, SessionRow, failed_row, find_sessions, is_done
from lapreco_hil.batch.summary import format_markdown, write_summary
from lapreco_hil.cli.main import main
from lapreco_hil.errors import ConfigError

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SESSIONS = ("skull-0", "skull-1", "skull-2")


@pytest.fixture(scope="module")
def sessions_dir(tmp_path_factory, warp_cpu):
    """Three tiny simulated skull sessions with ground truth (16 frames at 8 fps, 192x144: about 100 inliers
    each), one broken session (a session.json without its fields) and a folder that is not a session."""
    from lapreco_hil.app.record import sim_record

    root = tmp_path_factory.mktemp("batch") / "sessions"
    for seed, name in enumerate(SESSIONS):
        sim_record("skull", str(root / name), frames=16, fps=8.0, resolution=(192, 144), seed=seed,
                   device=warp_cpu, progress=False)
    (root / "broken").mkdir()
    (root / "broken" / "session.json").write_text(json.dumps({"format": "lapreco-session", "version": 1}))
    (root / "notes").mkdir()
    return root


def read_csv(path):
    with open(path, newline="") as fh:
        return {r["session"]: r for r in csv.DictReader(fh)}


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("lapreco: error: ")
    return err[0]


def test_find_sessions_lists_session_folders_and_refuses_a_missing_or_empty_folder(sessions_dir, tmp_path):
    sessions, others = find_sessions(sessions_dir)
    assert [p.name for p in sessions] == ["broken", *SESSIONS] and [p.name for p in others] == ["notes"]
    with pytest.raises(ConfigError, match="does not exist"):
        find_sessions(tmp_path / "nowhere")
    (tmp_path / "empty" / "just-a-folder").mkdir(parents=True)
    with pytest.raises(ConfigError, match="holds no session"):
        find_sessions(tmp_path / "empty")
    with pytest.raises(ConfigError, match="is one session"):
        find_sessions(sessions_dir / "skull-0")


@pytest.mark.parametrize("case,expected", [("missing", "does not exist"), ("empty", "holds no session")])
def test_the_cli_says_in_one_line_that_there_are_no_sessions(case, expected, tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["batch", str(tmp_path / case), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert expected in one_error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_an_unreachable_address_or_a_bad_option_is_one_line(sessions_dir, tmp_path, capsys):
    with socket.socket() as s:  # a loopback port that nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = ["batch", str(sessions_dir), "--out", str(tmp_path / "out"), "--no-progress"]
    assert main([*argv, "--address", f"127.0.0.1:{port}"]) == 2
    line = one_error_line(capsys)
    assert f"--address 127.0.0.1:{port}: cannot reach a Ray cluster there" in line and "ray start --head" in line
    assert main([*argv, "--address", "no-port-here"]) == 2
    assert "expected HOST:PORT" in one_error_line(capsys)
    assert main([*argv, "--address", "auto", "--workers", "2"]) == 2
    assert "--workers sizes a local Ray instance" in one_error_line(capsys)
    assert main([*argv, "--config", str(tmp_path / "missing.toml")]) == 2  # refused before Ray starts
    assert "missing.toml" in one_error_line(capsys)


def test_one_session_in_process_writes_its_outputs_and_done_file_last(sessions_dir, tmp_path, warp_cpu):
    options = BatchOptions(tracker="opencv", device=warp_cpu)
    row = process_session(str(sessions_dir / "skull-0"), str(tmp_path / "skull-0"), options)
    assert row.status == "ok" and row.error == "" and row.frames == 16 and row.inliers > 20
    assert row.rms_mm > 0 and row.camera_mm > 0 and 0 < row.coverage <= 1 and row.icp_rms_mm > 0
    assert row.latency_p99_ms >= row.latency_p50_ms > 0 and row.fps > 0 and row.wall_s > 0 and row.cpu_s > 0
    assert is_done(tmp_path / "skull-0")
    (tmp_path / "skull-0" / DONE_FILE).unlink()  # as if the run died after report.json: not done
    assert not is_done(tmp_path / "skull-0")

    bad = process_session(str(sessions_dir / "broken"), str(tmp_path / "broken"), options)
    assert bad.status == "failed" and "session.json" in bad.error and "\n" not in bad.error
    assert not is_done(tmp_path / "broken")


def test_the_table_and_plots_show_every_row(tmp_path):
    rows = [SessionRow("a", "ok", frames=10, inliers=120, rms_mm=0.9, coverage=0.42, camera_mm=0.1, fps=30.0,
                       latency_p50_ms=12.0, latency_p99_ms=40.0, wall_s=3.0),
            SessionRow("b", "ok", earlier=True, frames=10, inliers=80, wall_s=2.0),
            failed_row("c", "c/session.json: bad | field\nsecond line")]
    md = format_markdown(rows, "t")
    assert "| a | ok | 10 | 120 | 0.90 | 42% | 0.100 | 30.0 | 12.0 | 40.0 | 3.0 |  |" in md
    assert "| b | ok (earlier run) | 10 | 80 |" in md
    assert "| c | failed |" in md and "bad \\| field second line" in md
    paths = write_summary(rows, tmp_path, "t")
    assert list(read_csv(paths["csv"])) == ["a", "b", "c"]
    for kind in ("quality_plot", "latency_plot"):
        assert paths[kind].read_bytes()[:8] == PNG_MAGIC


def test_the_other_commands_do_not_import_ray():
    code = ("import sys, lapreco_hil.cli.main, lapreco_hil.app.batch; "
            "sys.exit('ray' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_gpus_a_local_instance_lacks_are_refused_instead_of_waiting(sessions_dir, tmp_path, monkeypatch):
    # a local instance that sees no GPU, whatever this machine has
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    with pytest.raises(ConfigError, match="no node of a local Ray instance has 1 CPU and 1 GPUs"):
        run_batch(str(sessions_dir), str(tmp_path / "out"), workers=1, gpus_per_task=1.0, progress=False)
    import ray  # (imported here, after the app: imported first, it would keep Ray off loopback-only)

    assert not ray.is_initialized()  # the local instance is shut down after the error too


@pytest.mark.slow
def test_a_batch_on_two_local_ray_workers_resumes_and_redoes_with_force(sessions_dir, tmp_path, capsys,
                                                                          monkeypatch):
    out = tmp_path / "out"
    monkeypatch.chdir(tmp_path)  # a relative --config must reach the tasks, whose working folder is another
    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:9")  # only --address picks a cluster; this is ignored
    # 16 frames count as few views, so the report shows the corner budget of this config; the sparse map's
    # surface (the dense one is tested on its own: here it only cost time)
    (tmp_path / "batch.toml").write_text("[tracker.few_views]\nframes = 16\nmax_features = 1500\n"
                                         "[surface]\nmode = \"alpha\"\n")
    argv = ["batch", str(sessions_dir), "--out", str(out), "--workers", "2", "--tracker", "opencv",
            "--device", "auto", "--config", "batch.toml", "--no-progress"]
    assert main(argv) == 1  # the broken session failed; the others ran
    captured = capsys.readouterr()
    assert "4 sessions: 3 ok (0 done before), 1 failed (broken); 4 replayed" in captured.out
    # the local instance is loopback-only (no server on another interface) and has the 2 workers asked for
    assert "a local Ray instance (1 node at 127.0.0.1, 2 CPUs" in captured.out
    assert captured.err.strip().startswith("lapreco: error: 1 of 4 sessions failed; first: broken: ")
    rows = read_csv(out / "summary.csv")
    assert list(rows) == ["broken", *SESSIONS]
    for name in SESSIONS:
        r = rows[name]
        assert r["status"] == "ok" and r["error"] == "" and r["earlier"] == "False"
        assert int(r["inliers"]) > 20 and float(r["rms_mm"]) > 0 and float(r["camera_mm"]) > 0
        assert r["coverage"] and float(r["latency_p50_ms"]) > 0 and r["device"] == "cpu"
        assert is_done(out / name) and (out / name / "points.ply").is_file()
        assert json.loads((out / name / "report.json").read_text())["few_views"]["max_features"] == 1500
    assert rows["broken"]["status"] == "failed" and "session.json: field" in rows["broken"]["error"]
    assert not (out / "broken" / DONE_FILE).exists()
    md = (out / "summary.md").read_text()
    assert "| session | status | frames | inliers | RMS mm | coverage | camera error mm |" in md
    for name in ("inliers_rms.png", "latency.png"):
        assert (out / name).read_bytes()[:8] == PNG_MAGIC

    reports = {name: (out / name / "report.json").stat().st_mtime_ns for name in SESSIONS}
    assert main(argv) == 1  # resumed: the done sessions are read back, the failed one is tried again
    assert "3 ok (3 done before), 1 failed (broken); 1 replayed" in capsys.readouterr().out
    assert {name: (out / name / "report.json").stat().st_mtime_ns for name in SESSIONS} == reports
    assert all(r["earlier"] == "True" for n, r in read_csv(out / "summary.csv").items() if n != "broken")
    assert "| skull-0 | ok (earlier run) |" in (out / "summary.md").read_text()

    assert main([*argv, "--force"]) == 1
    assert "3 ok (0 done before), 1 failed (broken); 4 replayed" in capsys.readouterr().out
    redone = {name: (out / name / "report.json").stat().st_mtime_ns for name in SESSIONS}
    assert all(redone[name] > reports[name] for name in SESSIONS)
