"""One folder of a study, as it runs on a Dask worker: skip it if up to date, else fit it.

The worker side of a study (app/study.py). A task never raises: every outcome, a
failure included, comes back as a `FolderReport` (a plain dict, so that the client needs
nothing of the worker's state). The fit itself is the pipeline of `stairfit fit`
(`load_scene`, `check_photos`, `fit_scene` into a staged folder), so each folder's result is
exactly what `stairfit fit` writes.

"Complete and matching" (docs/study.md §Resuming): `OUT/NAME/results.json` exists (the folder
gets its name only after every file is written), the ledger `OUT/.stairfit-study/NAME.json`
(written after the folder is in place) holds the same fingerprint as the folder's inputs now,
and results.json's scene SHA-256 equals the ledger's. The fingerprint is the SHA-256 of
scene.toml and of every file of `Scene.input_files()`, the stairfit version and the fit
options that change a result (the whole preset, posterior, forced model, model-error term,
seed).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import resource
import socket
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from . import __version__
from .errors import UserError

if TYPE_CHECKING:
    from ._jsontypes import JSONObject, JSONValue, Record
    from .outcome import FitOptions
    from .scene import Scene

LEDGER_DIR = ".stairfit-study"
"""Folder of OUT holding one ledger file per finished folder (its inputs' fingerprint)."""
RESULTS = "results.json"

FITTED, SKIPPED, FAILED, INTERRUPTED = "fitted", "skipped", "failed", "interrupted"
"""A folder's status in the study table: fitted now, skipped (up to date), failed (with its
one-line error), or interrupted (not finished when the study was stopped)."""


class FolderReport(TypedDict, total=False):
    """What a task returns: `folder`, `output`, `status`, `error`, `note`, `scene` (layer_um,
    material, metadata, ...), `results` (the folder's results.json, or None) and `run` (timing
    and worker diagnostics)."""

    folder: str
    output: str
    status: str
    error: str | None
    note: str | None
    scene: Record | None
    results: JSONObject | None
    run: Record


log = logging.getLogger("stairfit.study")


@dataclass(frozen=True)
class FolderTask:
    """What a worker needs to fit one photo folder of a study.

    `folder` is the photo folder and `out` the study folder (both absolute: every worker must
    see them at these paths); `name` is the folder's result folder inside `out`; `refit` fits
    even when the result is up to date (`--force`); `jax_cache` is the shared persistent JAX
    compilation cache (None: off); `version` the client's stairfit version.
    """

    folder: Path
    out: Path
    name: str
    options: FitOptions
    refit: bool
    jax_cache: str | None
    version: str


def run_task(task: FolderTask) -> FolderReport:
    """Fit (or skip) one folder; never raises: a failure is reported with its one-line error."""
    started = time.time()
    report: FolderReport = {
        "folder": str(task.folder),
        "output": task.name,
        "status": FAILED,
        "error": None,
        "note": None,
        "scene": None,
        "results": None,
    }
    cache = None
    try:
        cache = prepare_worker(task)
        report.update(fit_or_skip(task))
    except Exception as err:  # a failed folder must not stop the others
        report["error"] = describe_error(err, task)
    report["run"] = run_info(started) | {"jax_cache": cache}
    return report


def prepare_worker(task: FolderTask) -> str | None:
    """float64, the faster-compiling emitters and the shared JAX cache in this worker process
    (idempotent), version check.

    Returns the cache folder in use, None when it is off or cannot be created on this worker.
    """
    if task.version != __version__:
        raise UserError(
            f"this worker ({socket.gethostname()}) runs stairfit {__version__}, the study "
            f"stairfit {task.version}; install the same version on every worker"
        )
    from ._jaxcache import ENV_VAR, enable_persistent_cache, fast_compile

    fast_compile()  # a worker started by the user (a LocalCluster's inherit it from the study)
    import jax

    jax.config.update("jax_enable_x64", True)  # [conventions §10]
    folder = enable_persistent_cache({ENV_VAR: task.jax_cache or "off"})
    return None if folder is None else str(folder)


def fit_or_skip(task: FolderTask) -> FolderReport:
    """The folder's status, scene summary and results (the fit runs only when needed)."""
    from .outputs import staged_folder
    from .pipeline import check_photos, fit_scene
    from .scene import load_scene

    scene = load_scene(task.folder)
    summary = scene_summary(scene)
    dest = task.out / task.name
    ledger = task.out / LEDGER_DIR / f"{task.name}.json"
    fingerprint = input_fingerprint(scene, task.options)
    if not task.refit and up_to_date(dest, ledger, fingerprint):
        return {"status": SKIPPED, "scene": summary, "results": read_results(dest)}
    note = replaced_note(dest, ledger, fingerprint, task.refit)
    check_photos(scene)
    ledger.unlink(missing_ok=True)  # the old fingerprint no longer describes dest
    # a worker goes on to further folders: it does not freeze what it imported (what is
    # frozen is never collected)
    options = dataclasses.replace(task.options, progress=False, freeze_imports=False)
    with staged_folder(dest, force=True, command="fit") as tmp:
        fit_scene(scene, tmp, options)
    write_ledger(ledger, task, fingerprint)
    return {"status": FITTED, "scene": summary, "results": read_results(dest), "note": note}


def scene_summary(scene: Scene) -> Record:
    """What the study table shows of a scene besides the fit: layer, material, metadata."""
    spec = scene.specimen
    material = spec.index.name if spec.index.model == "named" else spec.index.model
    return {
        "layer_um": spec.layer_um,
        "material": material,
        "wedges_deg": [w.angle_deg for w in spec.wedges],
        "n_photos": len(scene.photos),
        "metadata": dict(spec.metadata),
    }


def options_fingerprint(options: FitOptions) -> Record:
    """The fit options that change a result (not: progress bars, decoding processes, cache)."""
    return {
        "preset": options.preset.as_dict(),
        "posterior": options.posterior,
        "model": options.model,
        "kernel": options.kernel,
        "model_error": options.model_error,
        "seed": options.seed,
    }


def input_fingerprint(scene: Scene, options: FitOptions) -> JSONObject:
    """SHA-256 of the scene file and every input file, the stairfit version and the options.

    Input files are named relative to the photo folder where they lie inside it (so that a
    study folder moved as a whole keeps its fingerprints), else by absolute path.
    """
    from .outcome import sha256_of

    files = {}
    for path in scene.input_files():
        try:
            key = str(path.relative_to(scene.folder.resolve()))
        except ValueError:
            key = str(path)
        files[key] = sha256_of(path) if path.is_file() else None
    fingerprint = {
        "stairfit_version": __version__,
        "options": options_fingerprint(options),
        "scene_sha256": sha256_of(scene.path),
        "input_files_sha256": files,
    }
    return json.loads(json.dumps(fingerprint))  # tuples -> lists, as read back from a ledger


def read_json(path: Path) -> JSONValue:
    """The parsed JSON file, or None when it is absent or unreadable."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def up_to_date(dest: Path, ledger: Path, fingerprint: JSONObject) -> bool:
    """Whether `dest` holds a complete result of exactly these inputs (module docstring)."""
    results = read_json(dest / RESULTS)
    recorded = read_json(ledger)
    if not isinstance(results, dict) or not isinstance(recorded, dict):
        return False
    scene_sha = results.get("inputs", {}).get("scene", {}).get("sha256")
    return recorded.get("fingerprint") == fingerprint and scene_sha == fingerprint["scene_sha256"]


def replaced_note(dest: Path, ledger: Path, fingerprint: JSONObject, refit: bool) -> str | None:
    """Why an existing result is replaced (said in the table, never silently), or None."""
    if not dest.exists():
        return None
    if refit:
        return "replaced the existing result (--force)"
    recorded = read_json(ledger)
    if not isinstance(recorded, dict) or not isinstance(recorded.get("fingerprint"), dict):
        return "replaced a result without a study ledger (incomplete or made outside the study)"
    old = recorded["fingerprint"]
    changed = [key for key in fingerprint if old.get(key) != fingerprint[key]]
    what = ", ".join(changed) if changed else "results.json"
    return f"replaced an out-of-date result ({what} changed)"


def write_ledger(ledger: Path, task: FolderTask, fingerprint: JSONObject) -> None:
    """Record the fingerprint of the inputs `task.name` was fitted from (atomically)."""
    from .outputs import atomic_text

    record = {"folder": str(task.folder), "output": task.name, "fingerprint": fingerprint}
    with atomic_text(ledger) as fh:
        json.dump(record, fh, indent=2)


def read_results(dest: Path) -> JSONObject | None:
    """The folder's results.json (None if it cannot be read)."""
    results = read_json(dest / RESULTS)
    return results if isinstance(results, dict) else None


def describe_error(err: BaseException, task: FolderTask) -> str:
    """The one-line error of a failed folder, as `stairfit fit` would print it; the traceback
    of an internal error goes to a file beside the ledger (never to the study's terminal)."""
    from .errors import one_line

    imaging = sys.modules.get("stairfit.imaging")
    if isinstance(err, UserError) or (imaging and isinstance(err, imaging.ImagingError)):
        return one_line(str(err))
    if isinstance(err, OSError):
        where = f"{os.fsdecode(err.filename)}: " if err.filename else ""
        return one_line(where + (err.strerror or str(err)))
    trace = task.out / LEDGER_DIR / f"{task.name}.error.txt"
    try:
        from .fileio import atomic_text

        with atomic_text(trace) as fh:
            fh.write("".join(traceback.format_exception(err)))
        kept = f"the traceback is in {trace}"
    except OSError:
        log.debug("stairfit study: internal error while fitting %s", task.folder, exc_info=err)
        kept = f"the traceback is in the debug log of the worker on {socket.gethostname()}"
    return one_line(f"internal error ({type(err).__name__}: {err}); {kept}; please report it")


def run_info(started: float) -> Record:
    """Where and how long the task ran, and the worker process's peak memory so far."""
    peak_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "started": started,
        "elapsed_s": time.time() - started,
        "peak_rss_mb": peak_kib / 1024,
    }
