"""`stairfit study ROOT_OR_FOLDERS... -o OUT`: many photo folders, one Dask task each.

Every photo folder (a folder holding scene.toml; a ROOT is searched for them) is fitted as by
`stairfit fit` into `OUT/NAME`, one task per folder on Dask distributed: a `LocalCluster` of
spawned single-threaded worker processes by default (JAX does not survive fork), or an existing
cluster (`--scheduler`, `--scheduler-file`). Up-to-date results are skipped, failures recorded
with their one-line error, and the study table and page are written at the end
(app/commands/study_report.py). docs/study.md describes every rule.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import os
import re
import time
import uuid
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .. import __version__
from .._signals import Terminated
from ..errors import UserError
from ..fileio import resolved
from ..scene import SCENE_FILE
from ._study_task import FAILED, FITTED, INTERRUPTED, LEDGER_DIR, SKIPPED, FolderReport, FolderTask

if TYPE_CHECKING:
    from distributed import Client, Future, LocalCluster

CONNECT_TIMEOUT_S = 20
"""How long to wait for an existing scheduler to answer."""
WORKER_LOSS_S = 120.0
"""How long a study waits, with folders still to fit, while the cluster has no worker at all,
before it stops: a worker started without a nanny that died does not come back."""
POLL_S = 0.5
"""How often a study looks at the cluster while it waits for results."""
MEMORY_PER_WORKER_GIB = 1.0
"""Memory a local worker needs for a fit; with the cores it bounds --local-workers."""


class WorkersLostError(ConnectionError):
    """The cluster has had no worker for `WORKER_LOSS_S` with tasks still to run."""


SKIP_DIRS = frozenset({".stairfit-cache", LEDGER_DIR})


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


@dataclass(frozen=True)
class StudyPlan:
    """The validated study: its folder, one task per photo folder, and where it runs."""

    out: Path
    tasks: tuple[FolderTask, ...]
    scheduler: str | None
    scheduler_file: Path | None
    local_workers: int
    progress: bool


def run(args: argparse.Namespace) -> int:
    """`stairfit study`: 0 when every folder is fitted or up to date, 1 when any failed."""
    from .study_report import print_summary, write_study

    plan = plan_study(args)
    from ..outputs import output_lock

    reports: list[FolderReport] = []
    lost = None
    try:
        with output_lock(plan.out), connect(plan) as client:
            prepare_output(plan.out)  # only once a cluster is there: a failed start leaves none
            try:
                run_tasks(client, plan, reports)
            except WorkersLostError as err:  # report what finished, then say it in one line
                lost = err
                reports = with_interrupted(plan, reports)
    except (KeyboardInterrupt, Terminated):  # Ctrl-C, SIGTERM, SIGHUP: the same clean-up
        sweep_partial_folders(plan)
        write_study(plan.out, with_interrupted(plan, reports))
        raise
    sweep_partial_folders(plan)
    write_study(plan.out, reports)
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
    cache = jax_cache_folder(args.jax_cache)
    names = output_names(folders)
    tasks = tuple(
        FolderTask(folder, out, names[folder], options, args.force, cache, __version__)
        for folder in folders
    )
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
    after `CONNECT_TIMEOUT_S` of waiting); `option` names where it came from."""
    shown = _short(address)
    rest = address.split("://", 1)[1] if "://" in address else address
    host, _, port = rest.rpartition(":") if ":" in rest else (rest, "", "")
    if not address.strip() or not (host or rest).strip():
        raise UserError(
            f"{option}: {shown!r} is empty; give the scheduler's address, e.g. "
            "tcp://192.168.1.10:8786, or leave --scheduler out for a local cluster"
        )
    if port and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise UserError(
            f"{option}: {shown!r} has port {_short(port, 20)!r}; a port is a number from 1 "
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


def _short(text: str, limit: int = 100) -> str:
    """`text` cut to `limit` characters for a message."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


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


# --- folders --------------------------------------------------------------------------------


def find_folders(paths: Sequence[Path], exclude: Path | None = None) -> tuple[Path, ...]:
    """The photo folders named or found below the given paths (resolved, sorted, unique).

    A path that holds scene.toml (or is one) is a photo folder; any other folder is searched
    for photo folders, not below one, skipping hidden folders and `exclude` (the study
    folder). A path that does not exist, or under which nothing is found, is a user error.
    """
    found: set[Path] = set()
    for path in paths:
        path = Path(path).expanduser()
        if not path.exists():
            raise UserError(f"{path}: no such folder; give photo folders or a folder of them")
        path = resolved(path)
        if path.is_file():
            if path.name != SCENE_FILE:
                raise UserError(f"{path}: not a folder; give photo folders (with {SCENE_FILE})")
            path = path.parent
        below = set(_search(path, exclude))
        if not below:
            raise UserError(
                f"{path}: no {SCENE_FILE} in it or below it; give photo folders (each with its "
                f"{SCENE_FILE}) or a folder that holds them"
            )
        found |= below
    return tuple(sorted(found))


def _search(root: Path, exclude: Path | None) -> Iterator[Path]:
    """Photo folders at or below `root` (os.walk, not below a photo folder)."""
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        if SCENE_FILE in files:
            dirs[:] = []
            yield here
            continue
        dirs[:] = sorted(
            d
            for d in dirs
            if not d.startswith(".") and d not in SKIP_DIRS and (here / d) != exclude
        )


def output_name(folder: Path) -> str:
    """The folder's result folder inside OUT: its name and 8 hex digits of its path's hash.

    Stable (the same photo folder always gets the same name, whatever else is in the study)
    and unique (two folders of the same name in different places get different ones).
    """
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", folder.name).strip("._") or "folder"
    digest = hashlib.sha256(str(folder).encode("utf-8")).hexdigest()[:8]
    return f"{safe}-{digest}"


def output_names(folders: Sequence[Path]) -> dict[Path, str]:
    """`output_name` of every folder, checked to be unique."""
    names = {folder: output_name(folder) for folder in folders}
    if len(set(names.values())) != len(names):  # a hash collision: never silently merge two
        raise UserError("two photo folders got the same result name; rename one of them")
    return names


def check_output(out: Path, inputs: Sequence[Path] = ()) -> None:
    """Refuse an OUT that holds an input, the current or home folder (`outputs.check_output`),
    that is a file, or a non-empty folder that is not a study (never overwrite)."""
    from .. import outputs

    outputs.check_output(out, inputs, option="-o")
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder; choose another -o")
    if out.is_dir() and any(out.iterdir()) and not (out / LEDGER_DIR).is_dir():
        raise UserError(
            f"{out}: exists and is not a stairfit study folder (no {LEDGER_DIR}/); choose "
            "another -o, or an empty folder"
        )


def prepare_output(out: Path) -> None:
    """`check_output`, then create OUT and its ledger folder."""
    check_output(out)
    (out / LEDGER_DIR).mkdir(parents=True, exist_ok=True)


# --- the cluster ----------------------------------------------------------------------------


@contextmanager
def connect(plan: StudyPlan) -> Iterator[Client]:
    """A Dask client: of the given scheduler, or of a local cluster made (and closed) here."""
    from distributed import Client

    if plan.scheduler is None and plan.scheduler_file is None:
        quiet = not plan.progress
        with local_cluster(plan.local_workers, quiet) as cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(
            plan.scheduler,
            scheduler_file=None if plan.scheduler_file is None else str(plan.scheduler_file),
            timeout=CONNECT_TIMEOUT_S,
        )
    except (OSError, TimeoutError, ValueError) as err:
        option = "--scheduler" if plan.scheduler is not None else "--scheduler-file"
        raise UserError(
            f"{option}: cannot reach {where(plan)} ({_short(str(err), 300)}); start 'dask "
            "scheduler' and 'dask worker', or fix the address"
        ) from None
    with client:
        yield client


@contextmanager
def local_cluster(n_workers: int, quiet: bool = False) -> Iterator[LocalCluster]:
    """`n_workers` spawned worker processes of one thread each, no dashboard, quiet logs (only
    errors; with `quiet` only critical ones)."""
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn"}):
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.CRITICAL if quiet else logging.ERROR,
        )
    try:
        yield cluster
    finally:
        cluster.close()


def run_tasks(client: Client, plan: StudyPlan, reports: list[FolderReport]) -> None:
    """Submit every task and append the reports to `reports` as they finish (a bar of folders).

    The caller owns `reports`, so that on Ctrl-C (`KeyboardInterrupt` carries on up) it still
    has every report received; closing the client then releases the tasks not yet run.
    """
    from tqdm import tqdm

    from ._study_task import run_task

    token = uuid.uuid4().hex[:8]  # keys unique on a scheduler shared by several studies
    futures = {
        client.submit(run_task, task, key=f"stairfit-{task.name}-{token}", pure=False): task
        for task in plan.tasks
    }
    with tqdm(total=len(futures), desc="folders", unit="folder", disable=not plan.progress) as bar:
        for future in completed(client, futures, where(plan)):
            report = collect(future, futures[future])
            reports.append(report)
            bar.update()
            bar.set_postfix(counts(reports), refresh=False)
            if report["status"] == FAILED and plan.progress:
                bar.write(f"failed: {report['folder']}: {report['error']}")


def where(plan: StudyPlan) -> str:
    """The cluster in words, for messages."""
    if plan.scheduler is not None:
        return f"the scheduler {_short(plan.scheduler)}"
    if plan.scheduler_file is not None:
        return f"the scheduler in {plan.scheduler_file}"
    return "the local cluster"


def completed(
    client: Client,
    futures: dict[Future, FolderTask],
    cluster: str,
    worker_loss_s: float | None = None,
) -> Iterator[Future]:
    """The futures as they finish; `WorkersLostError` once the cluster has had no worker for
    `worker_loss_s` (default `WORKER_LOSS_S`) while some are still pending."""
    from distributed import as_completed

    limit = WORKER_LOSS_S if worker_loss_s is None else worker_loss_s
    pending = as_completed(futures)
    alone_since = None
    while not pending.is_empty():
        batch = pending.next_batch(block=False)
        yield from batch
        if batch or _worker_count(client) > 0:
            alone_since = None
        elif alone_since is None:
            alone_since = time.monotonic()
        elif time.monotonic() - alone_since > limit:
            left = sum(not f.done() for f in futures)
            raise WorkersLostError(
                f"{cluster} has had no worker for {limit:g} s with {left} folder(s) still to "
                "fit (a worker died, e.g. out of memory); start 'dask worker' (with its "
                "nanny, which restarts it) and run the study again: finished folders are kept"
            )
        if not batch:
            time.sleep(POLL_S)


def _worker_count(client: Client) -> int:
    """How many workers the scheduler knows now (0 when it cannot be asked)."""
    try:
        return len(client.scheduler_info().get("workers", {}))
    except Exception:  # a scheduler that went away has no workers either
        return 0


def collect(future: Future, task: FolderTask) -> FolderReport:
    """The task's report, or a failure report when the task could not run at all."""
    if future.status == "finished":
        return future.result()
    try:
        error = future.exception()
    except Exception as err:  # cancelled
        error = err
    return {
        "folder": str(task.folder),
        "output": task.name,
        "status": FAILED,
        "error": f"the cluster could not run the task ({type(error).__name__}: {error}); is "
        "the same stairfit installed on every worker, and did a worker die (memory)?",
        "note": None,
        "scene": None,
        "results": None,
        "run": None,
    }


def counts(reports: Sequence[FolderReport]) -> dict[str, int]:
    """How many folders have each status."""
    out = {s: 0 for s in (FITTED, SKIPPED, FAILED)}
    for r in reports:
        out[r["status"]] = out.get(r["status"], 0) + 1
    return out


def with_interrupted(plan: StudyPlan, reports: Sequence[FolderReport]) -> list[FolderReport]:
    """The reports received, and an `interrupted` row for every folder without one."""
    done = {r["output"] for r in reports}
    rows = list(reports)
    for task in plan.tasks:
        if task.name not in done:
            ledger = plan.out / LEDGER_DIR / f"{task.name}.json"
            finished = ledger.is_file() and (plan.out / task.name / "results.json").is_file()
            rows.append(
                {
                    "folder": str(task.folder),
                    "output": task.name,
                    "status": INTERRUPTED,
                    "error": "the study was interrupted before this folder's task reported",
                    "note": f"a result is in {task.name}/; the next run skips it if it is up "
                    "to date"
                    if finished
                    else None,
                    "scene": None,
                    "results": None,
                    "run": None,
                }
            )
    return rows


def sweep_partial_folders(plan: StudyPlan) -> None:
    """Clean what killed local workers left in OUT, as the next run into each folder would
    (`outputs.remove_stale_leftovers`: a complete result left aside is put back, incomplete
    staging folders are removed).

    Only for the local cluster, which is closed by now: on an existing cluster a task that was
    running when the study stopped goes on and finishes or removes its own staging folder (and
    holds its folder's lock meanwhile).
    """
    from ..outputs import output_lock, remove_stale_leftovers

    if plan.scheduler is not None or plan.scheduler_file is not None:
        return
    for task in plan.tasks:
        dest = plan.out / task.name
        try:
            with output_lock(dest):
                remove_stale_leftovers(dest)
        except (UserError, OSError):  # still locked by a live task, or not ours to clean
            continue
