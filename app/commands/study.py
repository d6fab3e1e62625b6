"""`stairfit study ROOT_OR_FOLDERS... -o OUT`: many photo folders, one Dask task each.

The command's options (those of `fit`, which pass through, and where the study runs) checked
into a `StudyPlan` before any cluster starts; the study itself is `stairfit.study.run_study`
(app/study.py). docs/study.md describes every rule.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..errors import UserError
from ..fileio import resolved
from ..study import StudyPlan, check_output, find_folders, make_tasks, run_study, shorten
from ..study_task import FAILED

MEMORY_PER_WORKER_GIB = 1.0
"""Memory a local worker needs for a fit; with the cores it bounds --local-workers."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register the `study` command (with every option of `fit`, which pass through)."""
    from ._fit_options import add_fit_options

    shared = argparse.ArgumentParser(add_help=False)
    add_fit_options(shared)
    p = sub.add_parser(
        "study",
        parents=[shared],
        help="fit many photo folders (a study of specimens) on a Dask cluster",
        description=(
            "Fit every photo folder (a folder with scene.toml; a ROOT is searched for them) as "
            "'stairfit fit' does, one Dask task per folder, into OUT/NAME; skip folders whose "
            "result is up to date; write OUT/study.csv and OUT/study.html (docs/study.md)."
        ),
        formatter_class=_HelpFormatter,
    )
    for action in p._actions:  # the shared options, said for a study
        if action.dest == "output":
            action.help, action.metavar, action.required = "study folder", "OUT", True
        elif action.dest == "force":
            action.help = "fit every folder again, even when its result is up to date"
        elif action.dest == "workers":
            action.help = "processes decoding photos within each task (keep 1; add Dask workers)"
    p.add_argument(
        "paths", nargs="+", type=Path, metavar="ROOT_OR_FOLDER", help="photo folders or roots"
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="use this Dask scheduler")
    where.add_argument(
        "--scheduler-file", type=Path, metavar="FILE", help="use the scheduler in this file"
    )
    p.add_argument(
        "--local-workers",
        type=int,
        default=None,
        metavar="N",
        help="worker processes of the local cluster (default: the number of cores)",
    )
    p.add_argument(
        "--jax-cache",
        default=None,
        metavar="DIR",
        help="shared JAX compilation cache of every worker ('off' disables it; default: "
        "$STAIRFIT_JAX_CACHE or ~/.cache/stairfit/jax)",
    )
    p.set_defaults(func=run)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults shown as `fit` shows them, except None (the help says it in words)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None:
            return action.help
        return super()._get_help_string(action)


def run(args: argparse.Namespace) -> int:
    """`stairfit study`: 0 when every folder is fitted or up to date, 1 when any failed."""
    from ..study_report import print_summary

    plan = plan_study(args)
    reports, lost = run_study(plan)
    print_summary(plan.out, reports)
    if lost is not None:
        raise lost
    return 1 if any(r["status"] == FAILED for r in reports) else 0


def plan_study(args: argparse.Namespace) -> StudyPlan:
    """Options, folders and tasks, every user mistake caught before a cluster starts."""
    from ._fit_options import options_from_args

    options = options_from_args(args)
    if args.workers != 1:
        raise UserError(
            "--workers: a study decodes each folder in its own task; keep --workers 1 and "
            "give more Dask workers (--local-workers, or workers of your cluster)"
        )
    if args.output is None:
        raise UserError("-o/--output: missing; give the study folder, e.g. -o study-results")
    local = check_local_workers(args.local_workers)
    if args.scheduler is not None:
        check_scheduler_address(args.scheduler)
    if args.scheduler_file is not None:
        check_scheduler_file(args.scheduler_file)
    out = resolved(args.output.expanduser())
    check_output(out)
    folders = find_folders(args.paths, exclude=out)
    check_output(out, folders)  # OUT must not be, or hold, a photo folder
    tasks = make_tasks(folders, out, options, args.force, jax_cache_folder(args.jax_cache))
    return StudyPlan(out, tasks, args.scheduler, args.scheduler_file, local, not args.quiet)


def check_local_workers(n: int | None) -> int:
    """`--local-workers` (default: the cores), at least 1 and at most what this machine runs:
    4 per core, and one per `MEMORY_PER_WORKER_GIB` of memory."""
    cores = cpu_cores()
    if n is None:
        return cores
    memory_gib = _memory_gib()
    most = max(1, min(4 * cores, int(memory_gib / MEMORY_PER_WORKER_GIB)))
    if not 1 <= n <= most:
        raise UserError(
            f"--local-workers: {n} is outside 1 to {most} (this machine has {cores} cores and "
            f"{memory_gib:.0f} GiB of memory; each worker fits one folder at a time); give at "
            f"most {most}, or add workers of a cluster (--scheduler)"
        )
    return n


def _memory_gib() -> float:
    """This machine's memory (GiB; 1024 where it cannot be read)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") / 2**30
    except (ValueError, OSError, AttributeError):
        return 1024.0


def check_scheduler_address(address: str, option: str = "--scheduler") -> None:
    """`--scheduler`: `[PROTOCOL://]HOST[:PORT]` with a port in 1-65535 (refused at once, not
    after `stairfit.study.CONNECT_TIMEOUT_S` of waiting); `option` names where it came from."""
    shown = shorten(address)
    rest = address.split("://", 1)[1] if "://" in address else address
    host, _, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
    if not address.strip() or not (host or rest).strip():
        raise UserError(
            f"{option}: {shown!r} is empty; give the scheduler's address, e.g. "
            "tcp://192.168.1.10:8786, or leave --scheduler out for a local cluster"
        )
    if port and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise UserError(
            f"{option}: {shown!r} has port {shorten(port, 20)!r}; a port is a number from 1 "
            "to 65535 (dask's default is 8786)"
        )


def check_scheduler_file(path: Path) -> None:
    """`--scheduler-file`: a JSON file with the scheduler's `address` (as `dask scheduler
    --scheduler-file` writes it)."""
    import json

    from ..fileio import describe, read_bytes

    start = f"start 'dask scheduler --scheduler-file {path}' first, or give the file it wrote"
    problem = describe(path)
    if problem is not None:
        raise UserError(f"--scheduler-file: {path} {problem}; {start}")
    try:
        info = json.loads(read_bytes(path, max_bytes=1 << 20))
    except (OSError, ValueError, RecursionError) as e:
        what = e.strerror if isinstance(e, OSError) and e.strerror else "is not valid JSON"
        raise UserError(f"--scheduler-file: {path} {what}; {start}") from None
    address = info.get("address") if isinstance(info, dict) else None
    if not isinstance(address, str):
        raise UserError(f"--scheduler-file: {path} names no scheduler 'address'; {start}")
    check_scheduler_address(address, f"--scheduler-file: {path}: address")


def cpu_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def jax_cache_folder(option: str | None) -> str | None:
    """The persistent JAX cache every worker uses, as an absolute path (None: off)."""
    from .._jaxcache import ENV_VAR, cache_dir

    environ = dict(os.environ) if option is None else {ENV_VAR: option}
    folder = cache_dir(environ)
    return None if folder is None else str(folder.expanduser().resolve())
