"""A study: many photo folders, each fitted as by `stairfit fit`, one Dask task each (the
library behind `stairfit study`, app/commands/study.py, which parses the options into a
`StudyPlan` and prints the summary).

Every photo folder (a folder holding scene.toml; a root is searched for them, `find_folders`) is
fitted into `OUT/NAME` (`output_name`) by a task on Dask distributed (app/study_task.py): a
`LocalCluster` of spawned single-threaded worker processes by default (JAX does not survive
fork), or an existing cluster. Up-to-date results are skipped, failures recorded with their
one-line error, and the study table and page are written at the end (app/study_report.py).
docs/study.md describes every rule.
"""

from __future__ import annotations

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

from ._signals import Terminated
from .errors import UserError
from .fileio import resolved
from .scene import SCENE_FILE
from .study_task import FAILED, FITTED, INTERRUPTED, LEDGER_DIR, SKIPPED, FolderReport, FolderTask

if TYPE_CHECKING:
    from distributed import Client, Future, LocalCluster

    from .outcome import FitOptions

CONNECT_TIMEOUT_S = 20
"""How long to wait for an existing scheduler to answer."""
WORKER_LOSS_S = 120.0
"""How long a study waits, with folders still to fit, while the cluster has no worker at all,
before it stops: a worker started without a nanny that died does not come back."""
POLL_S = 0.5
"""How often a study looks at the cluster while it waits for results."""


class WorkersLostError(ConnectionError):
    """The cluster has had no worker for `WORKER_LOSS_S` with tasks still to run."""


SKIP_DIRS = frozenset({".stairfit-cache", LEDGER_DIR})


@dataclass(frozen=True)
class StudyPlan:
    """The validated study: its folder, one task per photo folder, and where it runs."""

    out: Path
    tasks: tuple[FolderTask, ...]
    scheduler: str | None
    scheduler_file: Path | None
    local_workers: int
    progress: bool


def shorten(text: str, limit: int = 100) -> str:
    """`text` cut to `limit` characters for a message."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


# --- the study ------------------------------------------------------------------------------


def run_study(plan: StudyPlan) -> tuple[list[FolderReport], WorkersLostError | None]:
    """Fit every folder of `plan` on its cluster and write OUT/study.csv and OUT/study.html;
    the folders' reports, and the `WorkersLostError` that ended the study early (None when it
    ran to the end: the study's table then holds every folder, those not reached as
    `interrupted`). Ctrl-C, SIGTERM and SIGHUP write the table of what finished, clean up and
    carry on up."""
    from .outputs import output_lock
    from .study_report import write_study

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
    return reports, lost


def make_tasks(
    folders: Sequence[Path],
    out: Path,
    options: FitOptions,
    refit: bool,
    jax_cache: str | None,
) -> tuple[FolderTask, ...]:
    """One task per photo folder, each fitting into `out / output_name(folder)`."""
    from . import __version__

    names = output_names(folders)
    return tuple(
        FolderTask(folder, out, names[folder], options, refit, jax_cache, __version__)
        for folder in folders
    )


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
    from . import outputs

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
            f"{option}: cannot reach {where(plan)} ({shorten(str(err), 300)}); start 'dask "
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

    from .study_task import run_task

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
        return f"the scheduler {shorten(plan.scheduler)}"
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
    from .outputs import output_lock, remove_stale_leftovers

    if plan.scheduler is not None or plan.scheduler_file is not None:
        return
    for task in plan.tasks:
        dest = plan.out / task.name
        try:
            with output_lock(dest):
                remove_stale_leftovers(dest)
        except (UserError, OSError):  # still locked by a live task, or not ours to clean
            continue
