"""Benchmark: the demo's Observations refilled from the model itself (issue 13, fitting vs
measurement).

`bench_demo_calibration.py` fits the demo's photos. To separate what the fit does from what the
measurement does, this script takes the demo's own Observations (`stairfit demo --megapixels 2
--views 9 --seed S`'s photos, measured by the functions `stairfit fit` runs:
`stairfit.pipeline`'s `measure`, `observations`, `fit_setup`) and replaces every value by the
model at the truth (the fit's own spectral setup and aperture) plus Gaussian noise drawn with
the demo's errors: each ROI's channels with their standard errors and 3 x 3 correlation (`C = S
R S`, the covariance the fit whitens with). These `--draws` datasets per seed are fitted like
the demo (`fitting.select_model`, variant `sharp+floor` forced, model-error term free, the
balanced preset's starts) and the pulls of sigma, scale and floor summarised as in
bench_demo_calibration.py. Honest fitting gives pull mean 0 and sd 1 here whatever the photos
do; a bias that shows on photos but not here is the measurement's.

It also reports, for the photos' own Observations, the rows' mean whitened residual at the
truth per photo (a photo-common error moves all of a photo's rows together): the sd over
photos against the same figure on the model-data draws (which have none).

Outputs: benchmarks/results/demo_model_data.md and .json (benchmarks/results/quick/ with
`--quick`).

    python benchmarks/bench_demo_model_data.py [--seeds 0 1 2] [--draws 20] [--quick]
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_coverage import coverage_cell, pull_summary  # noqa: E402
from bench_demo_calibration import LS_LEVELS, MEGAPIXELS, VIEWS, load_text  # noqa: E402

DEG = math.pi / 180.0
VARIANT = "sharp+floor"
PARAMS = ("sigma_rad", "scale", "floor")


def demo_options() -> Any:
    """The FitOptions of `stairfit demo --megapixels 2 --views 9 --no-posterior --quiet` (the
    fit options' defaults: balanced preset, model-error term, seed 0, one decoding process)."""
    from stairfit.outcome import FitOptions
    from stairfit.presets import get_preset

    return FitOptions(
        preset=get_preset("balanced"),
        posterior=False,
        model=None,
        model_error=True,
        seed=0,
        workers=1,
        cache=True,
        progress=False,
    )


def demo_observations(seed: int, work: Path) -> tuple[Any, Any, Any, Any, dict[str, float]]:
    """Render the demo's photos of `seed`, measure them like `stairfit fit`: (observations,
    spectral, aperture, options, truth.json parameters)."""
    from stairfit import pipeline
    from stairfit import simulation as simulate
    from stairfit.scene import load_scene

    views = tuple(float(v) for v in np.linspace(-80.0, 20.0, VIEWS))
    settings = simulate.SimulationSettings(megapixels=MEGAPIXELS, views_deg=views, seed=seed)
    photos = work / f"photos{seed}"
    simulate.simulate(photos, settings, progress=False)
    options = demo_options()
    scene = load_scene(photos)
    table = pipeline.measure(scene, work / f"fit{seed}", options)
    observations = pipeline.observations(scene, table).data
    spectral, aperture = pipeline.fit_setup(scene, options.preset)[1:3]
    truth = json.loads((photos / simulate.TRUTH_FILE).read_text())["parameters"]
    return observations, spectral, aperture, options, truth


def truth_params(truth: dict[str, float]) -> Any:
    from stairfit import fitting

    return fitting.Params(
        sigma_rad=truth["sigma_deg"] * DEG,
        delta_n=truth.get("delta_n", 0.0),
        scale=truth["scale"],
        floor=truth["floor"],
    )


def group_covariances(obs: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """(row indices, covariance) of each ROI group (independent rows: groups of one)."""
    groups: list[tuple[np.ndarray, np.ndarray]] = []
    roi = np.asarray(obs.roi_index)
    se = np.asarray(obs.stderr, float)
    for r in np.unique(roi):
        rows = np.flatnonzero(roi == r) if r >= 0 else None
        if rows is None:
            groups += [(np.array([i]), np.array([[se[i] ** 2]])) for i in np.flatnonzero(roi < 0)]
            continue
        ch = np.asarray(obs.channel_index)[rows]
        i0 = rows[0]
        full = np.eye(3)
        full[0, 1] = full[1, 0] = obs.corr_01[i0]
        full[0, 2] = full[2, 0] = obs.corr_02[i0]
        full[1, 2] = full[2, 1] = obs.corr_12[i0]
        corr = full[np.ix_(ch, ch)]
        groups.append((rows, corr * np.outer(se[rows], se[rows])))
    return groups


def draw_noise(groups: list[tuple[np.ndarray, np.ndarray]], n: int, rng: Any) -> np.ndarray:
    """Gaussian errors with each group's covariance (eigen-clipped at 0: always drawable)."""
    out = np.zeros(n)
    for rows, cov in groups:
        w, v = np.linalg.eigh(cov)
        out[rows] = v @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(len(rows)))
    return out


def whitened_photo_means(obs: Any, model_values: np.ndarray, groups: list) -> np.ndarray:
    """Mean whitened residual (data - model, each ROI group whitened by its covariance's
    Cholesky factor) of the used rows of each photo."""
    res = np.asarray(obs.value, float) - model_values
    white = np.full(res.shape, np.nan)
    for rows, cov in groups:
        white[rows] = np.linalg.solve(np.linalg.cholesky(cov), res[rows])
    use = np.asarray(obs.use, bool)
    photo = np.asarray(obs.photo_index)
    return np.array([np.mean(white[use & (photo == p)]) for p in np.unique(photo[use])])


def chi2_parts(obs: Any, model_values: np.ndarray, groups: list) -> dict[str, float]:
    """The whitened chi^2 at `model_values` over the used rows of complete (3-channel) ROIs,
    split into each ROI's channel-common part (its generalised-least-squares mean relative
    residual over that mean's variance; 1 dof per ROI) and the rest, the channel differences
    (2 dof per ROI)."""
    v, use = np.asarray(obs.value, float), np.asarray(obs.use, bool)
    common = differences = 0.0
    n = 0
    for rows, cov in groups:
        if rows.size != 3 or not use[rows].all():
            continue
        mu = model_values[rows]
        rel = v[rows] / mu - 1.0
        inv = np.linalg.inv(cov / np.outer(mu, mu))
        one = np.ones(3)
        info = one @ inv @ one
        mean = one @ inv @ rel / info
        common += mean**2 * info
        differences += rel @ inv @ rel - mean**2 * info
        n += 1
    return {"common": float(common), "differences": float(differences), "rois": n}


def red_minus_blue(obs: Any, model_values: np.ndarray) -> dict[str, float]:
    """Per complete ROI ("photo/wedge"), the relative residual of R minus that of B at the
    truth: a channel difference that noise makes different in every seed and a systematic
    error (measurement or model) repeats."""
    v, use = np.asarray(obs.value, float), np.asarray(obs.use, bool)
    rel = v / model_values - 1.0
    out: dict[str, float] = {}
    roi, ch = np.asarray(obs.roi_index), np.asarray(obs.channel_index)
    for r in np.unique(roi[roi >= 0]):
        rows = np.flatnonzero(roi == r)
        by = {int(ch[i]): i for i in rows}
        if 0 in by and 2 in by and use[by[0]] and use[by[2]]:
            key = f"{int(obs.photo_index[by[0]])}/{int(obs.wedge_index[by[0]])}"
            out[key] = float(rel[by[0]] - rel[by[2]])
    return out


def seed_to_seed_correlation(per_seed: list[dict[str, float]]) -> list[float]:
    """The correlation over shared ROIs of consecutive seeds' `red_minus_blue`."""
    out = []
    for a, b in itertools.pairwise(per_seed):
        keys = sorted(set(a) & set(b))
        out.append(float(np.corrcoef([a[k] for k in keys], [b[k] for k in keys])[0, 1]))
    return out


def fit_pulls(obs: Any, spectral: Any, aperture: Any, options: Any, truth: Any) -> dict:
    """The demo's forced sharp+floor fit of `obs`: each parameter's pull and interval hits."""
    from stairfit import fitting

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fitting.FitWarningCategory)
        sel = fitting.select_model(
            obs,
            spectral,
            force=VARIANT,
            model_error=options.model_error,
            rounded_rungs=options.preset.rounded_rungs,
            sigma_starts_rad=tuple(s * DEG for s in options.preset.sigma_starts_deg),
            aperture=aperture,
            resolution=options.preset.rounded_resolution,
        )
    fit = sel.fit
    rec: dict[str, Any] = {"reduced_chi2": float(fit.reduced_chi2), "params": {}}
    for e in fit.estimates:
        if e.param == "model_error_frac":
            rec["model_error_frac"] = float(e.value)
        if e.param not in PARAMS or not e.stderr:
            continue
        t = float(np.mean(getattr(truth, e.param)))
        rec["params"][e.param] = {
            "pull": (e.value - t) / e.stderr,
            **{k: bool(abs(e.value - t) <= z * e.stderr) for k, (z, _) in LS_LEVELS.items()},
        }
    return rec


def summarize(recs: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for p in PARAMS:
        entries = [r["params"][p] for r in recs if p in r["params"]]
        out[p] = {
            "pull": pull_summary([e["pull"] for e in entries]),
            **{k: coverage_cell([e[k] for e in entries], nom) for k, (_, nom) in LS_LEVELS.items()},
        }
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--draws", type=int, default=20)
    p.add_argument("--quick", action="store_true", help="seed 0, 2 draws")
    p.add_argument("--out-dir", type=Path, default=None)
    args = p.parse_args(argv)
    from stairfit import fitting
    from stairfit._jaxcache import start_jax

    start_jax()
    seeds, draws = ([0], 2) if args.quick else (args.seeds, args.draws)
    out_dir = args.out_dir or (HERE / "results" / ("quick" if args.quick else ""))
    out_dir.mkdir(parents=True, exist_ok=True)
    meta = {"load_start": load_text(), "seeds": seeds, "draws": draws}
    t0 = time.perf_counter()
    model_recs: list[dict[str, Any]] = []
    photo_recs: list[dict[str, Any]] = []
    failed: list[dict[str, Any]] = []
    spread: dict[str, list[float]] = {"photos": [], "model_data": []}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            obs, spectral, aperture, options, truth_json = demo_observations(seed, Path(tmp))
            truth = truth_params(truth_json)
            mu = fitting.model_radiance(truth, obs, spectral, aperture=aperture)
            groups = group_covariances(obs)
            spread["photos"].append(float(np.std(whitened_photo_means(obs, mu, groups), ddof=1)))
            rec = fit_pulls(obs, spectral, aperture, options, truth)
            rb = red_minus_blue(obs, mu)
            photo_recs.append(
                {"seed": seed, "chi2_at_truth": chi2_parts(obs, mu, groups), "r_minus_b": rb, **rec}
            )
            print(f"seed {seed} photos: {rec}", flush=True)
            rng = np.random.default_rng(10_000 + seed)
            for k in range(draws):
                value = mu + draw_noise(groups, obs.n_rows, rng)
                sim = obs._replace(value=value)
                parts = chi2_parts(sim, mu, groups)
                spread["model_data"].append(
                    float(np.std(whitened_photo_means(sim, mu, groups), ddof=1))
                )
                try:
                    rec = fit_pulls(sim, spectral, aperture, options, truth)
                except fitting.FitError as err:  # counted and reported, not hidden
                    failed.append({"seed": seed, "draw": k, "error": str(err)})
                    print(f"seed {seed} draw {k}: FAILED {err}", flush=True)
                    continue
                model_recs.append({"seed": seed, "draw": k, "chi2_at_truth": parts, **rec})
                pulls = {q: round(v["pull"], 2) for q, v in rec["params"].items()}
                print(f"seed {seed} draw {k}: {pulls} (load {load_text()})", flush=True)
    meta["wall_s"] = time.perf_counter() - t0
    meta["load_end"] = load_text()
    result = {
        "meta": meta,
        "model_data": {"summary": summarize(model_recs), "records": model_recs},
        "photos": {"summary": summarize(photo_recs), "records": photo_recs},
        "photo_mean_spread": {k: float(np.mean(v)) for k, v in spread.items()},
        "failed": failed,
        "r_minus_b_seed_correlation": seed_to_seed_correlation(
            [r["r_minus_b"] for r in photo_recs]
        ),
        "r_minus_b_mean": [float(np.mean(list(r["r_minus_b"].values()))) for r in photo_recs],
    }
    (out_dir / "demo_model_data.json").write_text(json.dumps(result, indent=1))
    (out_dir / "demo_model_data.md").write_text(markdown(result))
    print(markdown(result))
    return 0


def markdown(result: dict[str, Any]) -> str:
    meta = result["meta"]
    lines = [
        "# Demo Observations refilled from the model (issue 13)",
        "",
        f"Seeds {meta['seeds']}, {meta['draws']} noise draws each, variant {VARIANT} forced, "
        f"model-error term free. Load (1/5/15 min) {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end; wall {meta['wall_s'] / 60:.1f} min. Method: the "
        "script's docstring.",
        "",
        "| data | parameter | pull mean +- se | pull sd | 68% | 95% |",
        "|---|---|---|---|---|---|",
    ]
    for what in ("model_data", "photos"):
        for p, s in result[what]["summary"].items():
            pu = s["pull"]
            cells = " | ".join(
                f"{s[k]['k']}/{s[k]['n']} [{s[k]['cp_low']:.2f}, {s[k]['cp_high']:.2f}]"
                for k in ("68", "95")
            )
            lines.append(f"| {what} | {p} | {pu['mean']:+.2f} +- {pu['mean_se']:.2f} | "
                         f"{pu['sd']:.2f} | {cells} |")  # fmt: skip
    sp = result["photo_mean_spread"]
    lines += [
        "",
        f"Sd over photos of the rows' mean whitened residual at the truth: photos "
        f"{sp['photos']:.3f}, model data {sp['model_data']:.3f} (mean over seeds / draws).",
        "",
        "Chi^2 at the truth (no model-error term) of complete 3-channel ROIs, split into the "
        "ROIs' channel-common part (1 dof each) and their channel differences (2 dof each), "
        "mean over seeds / draws: "
        + "; ".join(
            f"{what} common {np.mean([r['chi2_at_truth']['common'] for r in recs]):.1f}, "
            f"differences {np.mean([r['chi2_at_truth']['differences'] for r in recs]):.1f} "
            f"for {np.mean([r['chi2_at_truth']['rois'] for r in recs]):.1f} ROIs"
            for what, recs in (
                ("photos", result["photos"]["records"]),
                ("model data", result["model_data"]["records"]),
            )
        ),
        "",
        "Photos: R minus B relative residual at the truth per ROI, mean over ROIs per seed "
        + ", ".join(f"{1e4 * m:+.1f}e-4" for m in result["r_minus_b_mean"])
        + "; correlation over ROIs between consecutive seeds "
        + ", ".join(f"{c:.2f}" for c in result["r_minus_b_seed_correlation"])
        + " (noise alone: about 0).",
        "",
        f"Fits that raised: {len(result['failed'])}"
        + "".join(f"\n- seed {f['seed']} draw {f['draw']}: {f['error']}" for f in result["failed"]),
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
