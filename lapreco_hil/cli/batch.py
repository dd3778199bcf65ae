"""``lapreco batch``: arguments for :func:`lapreco_hil.app.batch.run_batch`, the table's path and a one-line
summary; exit status 1 when a session failed (the others still ran)."""

from __future__ import annotations

import sys

from lapreco_hil.cli.args import non_negative, positive_int


def cmd_batch(args) -> int:
    from lapreco_hil.app.batch import BatchOptions, run_batch

    result = run_batch(args.sessions_dir, args.out, address=args.address, workers=args.workers,
                       gpus_per_task=args.gpus_per_task, force=args.force, progress=not args.no_progress,
                       options=BatchOptions(tracker=args.tracker, device=args.device, config_path=args.config))
    print(f"lapreco batch: {result.summary_line()}; table in {result.paths['markdown']} and {result.paths['csv']}")
    if result.failed:
        first = result.failed[0]
        print(f"lapreco: error: {len(result.failed)} of {len(result.rows)} sessions failed; first: {first.session}: "
              f"{first.error}", file=sys.stderr)
        return 1
    return 0


def add_parser(sub) -> None:
    batch = sub.add_parser("batch", help="replay and evaluate every session of a folder as Ray tasks (local or a "
                                         "cluster): summary table and plots; resumable")
    batch.add_argument("sessions_dir", help="folder whose sub-folders are sessions (each with a session.json)")
    batch.add_argument("--out", required=True, help="output folder: one run folder per session, summary.csv, "
                                                    "summary.md, inliers_rms.png, latency.png")
    batch.add_argument("--address", default=None,
                       help="an existing Ray cluster (HOST:PORT of its head, ray://HOST:10001, or auto); default: "
                            "a local Ray instance on this machine")
    batch.add_argument("--workers", type=positive_int, default=None,
                       help="tasks at once on the local instance (its CPUs; default: this machine's cores)")
    batch.add_argument("--gpus-per-task", type=non_negative, default=0.0,
                       help="GPUs each task reserves, e.g. 1 or 0.5 (default 0: tasks run on the CPU)")
    batch.add_argument("--tracker", default="auto", help="warp | opencv | auto (default: auto)")
    batch.add_argument("--device", default="auto",
                       help="Warp device in each task: auto (cuda when the task has a GPU, else cpu) | cpu | cuda")
    batch.add_argument("--config", default=None, help="pipeline configuration (TOML), read by every task")
    batch.add_argument("--force", action="store_true", help="replay sessions that an earlier run finished, too")
    batch.add_argument("--no-progress", action="store_true", help="no progress bar")
    batch.set_defaults(func=cmd_batch)
