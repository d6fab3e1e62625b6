"""Benchmark: is the demo's scale pull a bias or one draw? (issue 13)

`stairfit demo --megapixels 2 --views 9` (seed 0) reported scale 2.26 standard errors below
its truth, outside its 95% interval. One seed cannot tell a bias from a 1-in-40 draw; this
script runs the same command for seeds 0..N-1 (each a fresh `stairfit demo` process: the
seed sets the photos' texture and noise and the posterior sampler; simulate + fit, posterior
on, the balanced preset, the model chosen as the demo chooses it) and collects from each
results.json, for every parameter with a truth in truth.json (sigma, scale, floor and
delta_n where the chosen model fits it):

* the least-squares estimate and standard error, its pull `(value - truth) / stderr` and
  whether `value +- 1 se` (68%) and `value +- 1.96 se` (95%) hold the truth;
* the posterior's median and its 16-84% and 2.5-97.5% intervals, whether they hold the truth;
* the chosen model, the reduced chi^2, the model-error term.

Per parameter: pull mean and sd (honest errors: 0 and 1; the mean's standard error is about
1 / sqrt(N), so |mean| > 3 / sqrt(N) flags a bias), and the 68% / 95% coverage with its 99%
Clopper-Pearson interval (`bench_coverage.clopper_pearson`, `coverage_cell`): a coverage is
judged off when the nominal value lies outside that interval. The JAX compilation cache is
shared by the runs (one temporary folder), so only the first compiles.

Outputs: benchmarks/results/demo_calibration.md and .json (benchmarks/results/quick/ with
`--quick`). The machine load is recorded at the start and the end (times are not the point).

    python benchmarks/bench_demo_calibration.py [--seeds 10] [--first-seed 0] [--out-dir DIR]
    python benchmarks/bench_demo_calibration.py --quick    # 2 seeds, no posterior: does it run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_coverage import coverage_cell, pull_summary  # noqa: E402

MEGAPIXELS = 2.0
VIEWS = 9
LS_LEVELS: dict[str, tuple[float, float]] = {"68": (1.0, 0.6827), "95": (1.959964, 0.95)}
"""Interval name -> (half-width in standard errors, nominal coverage), least squares."""
POSTERIOR_LEVELS: dict[str, tuple[str, str, float]] = {
    "68": ("p16", "p84", 0.68),
    "95": ("p2_5", "p97_5", 0.95),
}


def demo_command(out: Path, seed: int, posterior: bool) -> list[str]:
    """The `stairfit demo` command line of one seed (the issue's settings)."""
    exe = shutil.which("stairfit") or "stairfit"
    cmd = [exe, "demo", str(out), "--megapixels", f"{MEGAPIXELS:g}", "--views", str(VIEWS)]
    cmd += ["--seed", str(seed), "--quiet"]
    return cmd if posterior else [*cmd, "--no-posterior"]


def truth_key(param: str) -> str:
    """truth.json's name of a results.json parameter (sigma in degrees, like report.py)."""
    return "sigma_deg" if param == "sigma_rad" else param


def seed_record(results: dict[str, Any], truth: dict[str, float]) -> dict[str, Any]:
    """What one seed's results.json says about each parameter with a truth (pure)."""
    ls = results["diagnostics"]["least_squares"]
    rec: dict[str, Any] = {
        "chosen": results["model_selection"]["chosen"],
        "reduced_chi2": ls["reduced_chi2"],
        "chi2": ls["chi2"],
        "dof": ls["dof"],
        "model_error_frac": None,
        "params": {},
    }
    for p in results["parameters"]:
        if p["parameter"] == "model_error_frac":
            rec["model_error_frac"] = {
                "value": p["least_squares"]["value"],
                "stderr": p["least_squares"]["stderr"],
            }
        key = truth_key(p["parameter"])
        if key not in truth or p.get("wedge") is not None:
            continue
        t, value, se = truth[key], p["least_squares"]["value"], p["least_squares"]["stderr"]
        entry: dict[str, Any] = {"truth": t, "value": value, "stderr": se}
        if se:
            entry["pull"] = (value - t) / se
            entry["ls"] = {k: bool(abs(value - t) <= z * se) for k, (z, _) in LS_LEVELS.items()}
        post = p.get("posterior")
        if post is not None:
            entry["posterior"] = {k: post[k] for k in ("median", "p16", "p84", "p2_5", "p97_5")}
            entry["post"] = {
                k: bool(post[lo] <= t <= post[hi]) for k, (lo, hi, _) in POSTERIOR_LEVELS.items()
            }
            entry["post_pull"] = (post["median"] - t) / (0.5 * (post["p84"] - post["p16"]))
        rec["params"][key] = entry
    return rec


def run_seed(seed: int, work: Path, posterior: bool, env: dict[str, str]) -> dict[str, Any]:
    """One fresh `stairfit demo` process; its record plus the wall time."""
    out = work / f"seed{seed}"
    t0 = time.perf_counter()
    proc = subprocess.run(demo_command(out, seed, posterior), env=env, capture_output=True,
                          text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"seed {seed}: stairfit demo failed ({proc.returncode}):\n"
                         f"{proc.stderr[-3000:]}")  # fmt: skip
    results = json.loads((out / "fit" / "results.json").read_text())
    truth = json.loads((out / "photos" / "truth.json").read_text())["parameters"]
    shutil.rmtree(out)
    return {"seed": seed, "wall_s": wall, **seed_record(results, truth)}


def summarize(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Per parameter over seeds: pull mean/sd, least-squares and posterior coverage (pure)."""
    names = sorted({k for r in records for k in r["params"]})
    out: dict[str, Any] = {}
    for name in names:
        entries = [r["params"][name] for r in records if name in r["params"]]
        pulls = [e["pull"] for e in entries if "pull" in e]
        s: dict[str, Any] = {"n": len(entries), "pull": pull_summary(pulls) if pulls else None}
        if s["pull"] is not None:
            s["pull"]["bias_flag"] = bool(abs(s["pull"]["mean"]) > 3 / math.sqrt(len(pulls)))
        s["ls"] = {
            k: coverage_cell([e["ls"][k] for e in entries if "ls" in e], nominal)
            for k, (_, nominal) in LS_LEVELS.items()
            if any("ls" in e for e in entries)
        }
        s["post"] = {
            k: coverage_cell([e["post"][k] for e in entries if "post" in e], nominal)
            for k, (_, _, nominal) in POSTERIOR_LEVELS.items()
            if any("post" in e for e in entries)
        }
        post_pulls = [e["post_pull"] for e in entries if "post_pull" in e]
        s["post_pull"] = pull_summary(post_pulls) if post_pulls else None
        out[name] = s
    return out


def load_text() -> str:
    """The 1/5/15-minute load averages, for labelling."""
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def cell_text(c: dict[str, Any]) -> str:
    return (f"{c['k']}/{c['n']} = {c['coverage']:.2f} [{c['cp_low']:.2f}, {c['cp_high']:.2f}]"
            f"{'' if c['ok'] else ' **off**'}")  # fmt: skip


def markdown(meta: dict[str, Any], records: list[dict[str, Any]], summary: dict[str, Any]) -> str:
    """The results page."""
    n = len(records)
    lines = [
        "# Demo calibration over seeds (issue 13)",
        "",
        f"`stairfit demo --megapixels {MEGAPIXELS:g} --views {VIEWS} --seed S` for S = "
        f"{records[0]['seed']}..{records[-1]['seed']} ({n} seeds; posterior "
        f"{'on' if meta['posterior'] else 'off'}), stairfit {meta['version']}, commit "
        f"{meta['commit']}. Machine load (1/5/15 min) {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end (2 cores shared with other work); wall "
        f"{meta['wall_s'] / 60:.1f} min. Method: the script's docstring.",
        "",
        "## Per parameter",
        "",
        f"Pull = (least-squares value - truth) / stderr; a bias is flagged when |mean| > "
        f"3/sqrt(N) = {3 / math.sqrt(n):.2f}. Coverage: k/n = fraction [99% Clopper-Pearson].",
        "",
        "| parameter | n | pull mean +- se | pull sd | LS 68% | LS 95% | posterior 68% | "
        "posterior 95% |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in summary.items():
        pu = s["pull"]
        pull = "-" if pu is None else f"{pu['mean']:+.2f} +- {pu['mean_se']:.2f}"
        if pu is not None and pu["bias_flag"]:
            pull += " **bias?**"
        sd = "-" if pu is None else f"{pu['sd']:.2f}"
        cells = [cell_text(s[g][k]) if k in s[g] else "-" for g in ("ls", "post")
                 for k in ("68", "95")]  # fmt: skip
        lines.append(f"| {name} | {s['n']} | {pull} | {sd} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Per seed",
        "",
        "| seed | chosen | reduced chi^2 | model error (frac) | pulls (LS) | outside posterior "
        "95% |",
        "|---|---|---|---|---|---|",
    ]
    for r in records:
        me = r["model_error_frac"]
        me_text = "-" if me is None else f"{me['value']:.2g} +- {me['stderr'] or float('nan'):.2g}"
        pulls = ", ".join(f"{k} {e['pull']:+.2f}" for k, e in r["params"].items() if "pull" in e)
        outside = ", ".join(
            k for k, e in r["params"].items() if "post" in e and not e["post"]["95"]
        )
        lines.append(f"| {r['seed']} | {r['chosen']} | {r['reduced_chi2']:.3f} | {me_text} | "
                     f"{pulls} | {outside or '-'} |")  # fmt: skip
    chosen = {c: sum(r["chosen"] == c for r in records) for c in {r["chosen"] for r in records}}
    red = np.array([r["reduced_chi2"] for r in records])
    lines += [
        "",
        f"Chosen models: {', '.join(f'{k} x{v}' for k, v in sorted(chosen.items()))}. "
        f"Reduced chi^2: mean {red.mean():.3f}, range {red.min():.3f}..{red.max():.3f} "
        f"(dof {records[0]['dof']}: sd expected {math.sqrt(2 / records[0]['dof']):.3f}).",
        "",
    ]
    return "\n".join(lines)


def git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=HERE, text=True,
                              capture_output=True, check=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=10, help="number of seeds")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="2 seeds, no posterior")
    p.add_argument("--out-dir", type=Path, default=None)
    p.add_argument(
        "--report-only",
        action="store_true",
        help="rewrite the .md from the .json of an earlier (possibly partial) run",
    )
    args = p.parse_args(argv)
    from stairfit import __version__

    if args.report_only:
        return report_only(args.out_dir or HERE / "results")

    n = 2 if args.quick else args.seeds
    posterior = not args.quick
    out_dir = args.out_dir or (HERE / "results" / ("quick" if args.quick else ""))
    out_dir.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {"version": __version__, "commit": git_commit(),
                            "posterior": posterior, "load_start": load_text()}  # fmt: skip
    records: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        env = {**os.environ, "STAIRFIT_JAX_CACHE": str(work / "jax")}
        for seed in range(args.first_seed, args.first_seed + n):
            rec = run_seed(seed, work, posterior, env)
            records.append(rec)
            pulls = ", ".join(f"{k} {e['pull']:+.2f}" for k, e in rec["params"].items()
                              if "pull" in e)  # fmt: skip
            print(f"seed {seed}: {rec['chosen']}, reduced chi2 {rec['reduced_chi2']:.3f}, "
                  f"{pulls} ({rec['wall_s']:.0f} s, load {load_text()})", flush=True)  # fmt: skip
            partial = {"meta": meta, "records": records, "summary": summarize(records)}
            (out_dir / "demo_calibration.json").write_text(json.dumps(partial, indent=1))
    meta["wall_s"] = time.perf_counter() - t0
    meta["load_end"] = load_text()
    summary = summarize(records)
    (out_dir / "demo_calibration.json").write_text(
        json.dumps({"meta": meta, "records": records, "summary": summary}, indent=1)
    )
    (out_dir / "demo_calibration.md").write_text(markdown(meta, records, summary))
    print(markdown(meta, records, summary))
    return 0


def report_only(out_dir: Path) -> int:
    """The .md of the seeds an earlier run finished (a run stopped early writes its .json
    after every seed; its end load and wall time are then those of the last seed)."""
    data = json.loads((out_dir / "demo_calibration.json").read_text())
    meta, records = data["meta"], data["records"]
    meta.setdefault("load_end", "(stopped early: not recorded)")
    meta.setdefault("wall_s", sum(r["wall_s"] for r in records))
    summary = summarize(records)
    (out_dir / "demo_calibration.json").write_text(
        json.dumps({"meta": meta, "records": records, "summary": summary}, indent=1)
    )
    (out_dir / "demo_calibration.md").write_text(markdown(meta, records, summary))
    print(markdown(meta, records, summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
