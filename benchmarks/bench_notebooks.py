"""Benchmark: the notebooks on the test suite's small settings, and eager against compiled model
calls (issue 14: what the notebooks' cells cost a user, and the suite).

* every notebook in notebooks/ executed as tests/repository/test_notebooks.py executes it (nbclient,
  `STAIRFIT_NB_SMALL=1`, a fresh kernel each run; kernel start included), `--repeats` rounds
  interleaved; with `--baseline-ref REF` also the notebooks as stored at git REF (run with the
  installed stairfit), in the same rounds, side by side;
* the model evaluations of paper_figures' cells (diffuse curves of six wedges at 721 and 7201
  viewing angles, the sharp lobes at 357 incidence angles, a broadened BRDF at 20001 angles)
  called eagerly against through `jax.jit`, each in a fresh process (imports apart), interleaved.

    python benchmarks/bench_notebooks.py [--repeats 3] [--baseline-ref 0dd1f7d] [--out FILE]

Reports medians (range); the figures depend on the machine's load (say so when quoting them).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"

_MODEL_CALLS = """
import sys, time
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
from stairfit import model
DEG = np.pi / 180
compiled = sys.argv[1] == "compiled"
diffuse = jax.jit(model.diffuse_sharp) if compiled else model.diffuse_sharp
lobes = jax.jit(model.sharp_lobes) if compiled else model.sharp_lobes
brdf = jax.jit(model.brdf) if compiled else model.brdf
t0 = time.perf_counter()
for n_angles in (721, 7201):
    to = np.linspace(-90, 90, n_angles) * DEG
    for b in (10, 20, 30, 40, 45, 60):
        np.asarray(diffuse(to, b * DEG, 1.46))
for b in (10, 45):
    np.asarray(lobes(np.linspace(-89, 89, 357) * DEG, b * DEG, 1.46).ratio)
np.asarray(brdf(0.3, np.linspace(-90, 90, 20001) * DEG, 10 * DEG, 1.46, 5 * DEG))
print(time.perf_counter() - t0)
"""


def _run_notebook(path: Path) -> float:
    """Wall seconds to execute one notebook in a fresh kernel, small settings."""
    import nbclient
    import nbformat

    book = nbformat.read(path, as_version=4)
    with tempfile.TemporaryDirectory() as tmp:
        env = {"STAIRFIT_NB_SMALL": "1", "STAIRFIT_FIT_DIR": str(Path(tmp) / "no-such-fit"),
               "MPLBACKEND": "Agg", "TMPDIR": tmp}  # fmt: skip
        old = {k: os.environ.get(k) for k in env}
        os.environ.update(env)
        try:
            client = nbclient.NotebookClient(
                book, timeout=600, kernel_name="python3",
                resources={"metadata": {"path": str(NOTEBOOKS)}},
            )  # fmt: skip
            t0 = time.perf_counter()
            client.execute()
            return time.perf_counter() - t0
        finally:
            for k, v in old.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v


def _baseline_copy(ref: str, name: str, folder: Path) -> Path:
    """The notebook `name` as stored at git `ref`, written into `folder` (same name)."""
    text = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{ref}:notebooks/{name}"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    path = folder / name
    path.write_text(text)
    return path


def _model_calls(mode: str) -> float:
    """Seconds of paper_figures' model calls in a fresh process, imports apart."""
    out = subprocess.run([sys.executable, "-c", _MODEL_CALLS, mode], capture_output=True,
                         text=True, check=True)  # fmt: skip
    return float(out.stdout.strip().splitlines()[-1])


def _fmt(values: list[float]) -> str:
    return f"{statistics.median(values):.1f} s ({min(values):.1f}-{max(values):.1f})"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline-ref", help="also run the notebooks as stored at this git ref")
    ap.add_argument("--out", type=Path, help="write the table (Markdown) here too")
    args = ap.parse_args(argv)
    names = sorted(p.name for p in NOTEBOOKS.glob("*.ipynb"))
    runs: dict[tuple[str, str], list[float]] = {}
    calls: dict[str, list[float]] = {"eager": [], "compiled": []}
    with tempfile.TemporaryDirectory() as tmp:
        cases = [("now", name, NOTEBOOKS / name) for name in names]
        if args.baseline_ref:
            base = Path(tmp)
            cases += [(args.baseline_ref, n, _baseline_copy(args.baseline_ref, n, base))
                      for n in names]  # fmt: skip
        for r in range(args.repeats):
            for label, name, path in cases[r % len(cases) :] + cases[: r % len(cases)]:
                runs.setdefault((label, name), []).append(_run_notebook(path))
            for mode in ("eager", "compiled") if r % 2 == 0 else ("compiled", "eager"):
                calls[mode].append(_model_calls(mode))
    load = os.getloadavg()[0]
    lines = [
        f"# Notebooks on small settings ({datetime.now():%Y-%m-%d %H:%M}, load {load:.1f} at "
        f"the end, {args.repeats} rounds, median (range))",
        "",
        "| notebook | " + " | ".join(dict.fromkeys(label for label, _ in runs)) + " |",
        "|---|" + "---|" * len(dict.fromkeys(label for label, _ in runs)),
    ]
    for name in names:
        cells = [_fmt(runs[(label, name)]) for label in dict.fromkeys(lb for lb, _ in runs)]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if args.baseline_ref:
        lines += [
            "",
            f"{args.baseline_ref}: the notebooks as stored at that commit, run with the installed "
            "stairfit (library changes since then apply to both columns).",
        ]
    lines += [
        "",
        "paper_figures' model calls, fresh process each, imports apart: eager "
        f"{_fmt(calls['eager'])}, through jax.jit {_fmt(calls['compiled'])}",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
