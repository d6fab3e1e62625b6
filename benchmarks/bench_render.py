"""`stairfit render` cold, end to end (issue 41's "each in under 2 minutes"): every case a fresh
process with an empty JAX cache and a new output folder (so every material table is computed),
timed from outside (wall and CPU seconds, medians of `--repeats`).

The cases:

* `stairfit render FIT --photos PHOTOS`: the fitted material on the photographed specimen from
  every photo's view (the tables of the scene's wedges, then every view);
* `stairfit render FIT --mesh MESH` (default the tests' printed sphere, 512 x 512): a printed
  object, one table per 10-deg bin of its surfaces' wedge angles.

`--compare-exe OTHER/bin/stairfit` runs an earlier version's `stairfit` beside this one's: both
render the same fit, one after the other in every repeat, so a slow phase of the machine hits
both alike (install the earlier commit in its own environment: `git worktree add ../old
COMMIT`, a venv with `pip install -e "../old[dev]"`).

    python benchmarks/bench_render.py FIT --photos PHOTOS
    python benchmarks/bench_render.py FIT --photos PHOTOS --compare-exe ../oldvenv/bin/stairfit

Writes one block of results (Markdown) to stdout; benchmarks/results/render.md keeps
them, newest first.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

from _timing import timed

ROOT = Path(__file__).resolve().parents[1]
MESH = ROOT / "tests" / "data" / "printed_sphere.obj"


def cases(exe: str, fit: Path, photos: Path, mesh: Path) -> dict[str, list[str]]:
    """The commands of one installation (the output folder is appended per run)."""
    return {
        "specimen": [exe, "render", str(fit), "--photos", str(photos), "--quiet"],
        f"mesh {mesh.name}": [exe, "render", str(fit), "--mesh", str(mesh), "--quiet"],
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("fit", type=Path, help="a folder written by stairfit fit")
    p.add_argument("--photos", type=Path, required=True, help="the photos the fit read")
    p.add_argument("--mesh", type=Path, default=MESH)
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--compare-exe", help="an earlier version's stairfit script")
    args = p.parse_args(argv)
    here = shutil.which("stairfit", path=str(Path(sys.executable).parent))
    if here is None:
        raise SystemExit("no stairfit script beside this Python: run it from the project's venv")
    installs = {"this checkout": here}
    if args.compare_exe:
        if not os.access(args.compare_exe, os.X_OK):
            raise SystemExit(f"--compare-exe: {args.compare_exe} is not an executable file")
        installs["--compare-exe"] = args.compare_exe
    times: dict[tuple[str, str], list[tuple[float, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        for rep in range(args.repeats):
            for label, exe in installs.items():
                for case, cmd in cases(exe, args.fit, args.photos, args.mesh).items():
                    run = Path(tmp) / f"{rep}-{label[:4]}-{case[:4]}"
                    env = {**os.environ, "STAIRFIT_JAX_CACHE": str(run / "jax-cache")}
                    wall, _, cpu, _ = timed([*cmd, "-o", str(run / "out")], env)
                    result = (wall, cpu)
                    times.setdefault((case, label), []).append(result)
                    print(f"# {case}, {label}: {result[0]:.1f} s wall, {result[1]:.0f} s CPU",
                          file=sys.stderr, flush=True)  # fmt: skip
                    shutil.rmtree(run)
    print(f"`stairfit render` cold (empty JAX cache, tables computed), {args.repeats} run(s) "
          f"each, load average at the end {os.getloadavg()[0]:.2f}:\n")  # fmt: skip
    print("| case | " + " | ".join(installs) + " |")
    print("|---|" + "---|" * len(installs))
    for case in cases("x", args.fit, args.photos, args.mesh):
        cells = []
        for label in installs:
            runs = times[(case, label)]
            wall = statistics.median(r[0] for r in runs)
            cpu = statistics.median(r[1] for r in runs)
            cells.append(f"{wall:.1f} s ({cpu:.0f} s CPU)")
        print(f"| {case} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
